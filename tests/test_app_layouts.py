"""The app on the field's layouts, under AppTest: a database/queries dataset with a descriptor file.

GardensPoint is written in the database-queries layout in a temporary folder (links to the
real images, ``example_layouts``), its efficientnet-lite0 descriptors (computed by the
project) written to an ``.npz`` and typed in the app as a file of descriptors computed
elsewhere. Every number a page shows is compared with the library's (``retrieval_views``,
``pipeline.evaluate_retrieval``), the map's traces with the places and the ground truth;
bad input (a missing file, a file with missing images or NaN rows, a radius of -1 in the
link) is one message naming it, never a traceback.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import assert_clean, figure, fresh_caches, metric, navigation_mode, page, trace  # noqa: F401
from vpr_explorer.app import ENTRY
from vpr_explorer.descriptors.imported import write_descriptor_file
from vpr_explorer.data.example_layouts import utm_name, write_gardens_point_layouts
from vpr_explorer.data.aligned import database_queries
from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, open_dataset
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec
from vpr_explorer.views.numbers import (
    DEFAULT_GROUP_M,
    DEFAULT_STEP_M,
    RetrievalPlaces,
    database_label,
    explain_query,
    find_query,
    fit_retrieval,
    image_answer,
    overview,
    place_detail,
    place_queries,
    query_label,
)
from vpr_explorer.views.numbers import evaluation_rows

pytestmark = pytest.mark.realdata

TIMEOUT = 120
LATTICE = PlaceGeometry.LATTICE  # the default of unordered position-tagged data


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory) -> dict[str, Path]:
    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("gp_layouts"))


@pytest.fixture(scope="module")
def dq(layouts):
    return open_dataset(layouts["database-queries"])


@pytest.fixture(scope="module")
def dq_effnet(dq, gp_effnet):
    """efficientnet-lite0 of the 400 database-queries images (the session's cache serves them: same image content)."""
    return np.asarray(dataset_descriptors(dq, "efficientnet-lite0"))


@pytest.fixture(scope="module")
def npz(dq, dq_effnet, tmp_path_factory) -> Path:
    """The descriptors as a file made elsewhere: ``names`` relative to the dataset folder, ``descriptors``."""
    path = tmp_path_factory.mktemp("descriptors") / "effnet_gp.npz"
    write_descriptor_file(path, dq_effnet, dq.image_paths, dq.root)
    return path


def places(group=DEFAULT_GROUP_M, step=DEFAULT_STEP_M, geometry=LATTICE) -> RetrievalPlaces:
    return RetrievalPlaces(geometry, metric=MetricPlaceSpec(group, step, "stride", geometry))


def opened(source: Path, descriptors: Path | None = None, **params) -> AppTest:
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(source), **({"descriptors": str(descriptors)} if descriptors else {}),
                           **{k: str(v) for k, v in params.items()})
    return at.run()


def errors(at: AppTest) -> str:
    return "\n".join(e.value for e in at.error)


def image_captions(at: AppTest) -> list[str]:
    return [img.caption for element in at.image for img in element.proto.imgs]


# --------------------------------------------------------------------------- dataset page


def test_the_dataset_page_opens_the_layout_with_the_descriptor_file(layouts, npz):
    at = opened(layouts["database-queries"], npz)
    assert_clean(at)
    assert at.selectbox(key="w_layout").value == "auto"
    assert "detected: database-queries" in at.selectbox(key="w_layout").format_func("auto")
    assert at.radio(key="w_descriptor").value == "__file__" and at.text_input(key="w_descriptor_file").value == str(npz)
    assert any(f"effnet_gp descriptors ready: 400 × 1280 (read from {npz}" in s.value for s in at.success)
    assert any("200 database and 200 query images" in s.value for s in at.subheader)
    assert any("within 25 m" in c.value and "0 of 200 queries with no right database image" in c.value
               for c in at.caption)
    assert at.number_input(key="w_radius").value == 25.0
    sidebar = " ".join(c.value for c in at.sidebar.caption)
    assert "`effnet_gp`" in sidebar and str(npz) in sidebar
    assert at.session_state["view"].descriptor == "effnet_gp"  # the file's stem names it


def test_a_descriptor_file_typed_in_the_box_opens_and_picking_an_extractor_leaves_it(layouts, npz):
    at = opened(layouts["database-queries"])
    at.radio(key="w_descriptor").set_value("__file__").run()
    at.text_input(key="w_descriptor_file").input(str(npz)).run()
    assert_clean(at)
    assert at.query_params["descriptors"] == str(npz) and at.query_params["descriptor"] == "effnet_gp"
    at.radio(key="w_descriptor").set_value("pixels").run()
    assert_clean(at)
    assert "descriptors" not in at.query_params and at.session_state["view"].descriptor == "pixels"
    assert any("pixels descriptors ready: 400 × 2048" in s.value for s in at.success)


def test_a_descriptor_file_typed_for_aligned_traversals_names_every_page(demo, demo_pixels, tmp_path):
    path = tmp_path / "demo-export.h5"  # hloc's layout
    write_descriptor_file(path, demo_pixels, demo.image_paths, demo.root)
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    at.radio(key="w_descriptor").set_value("__file__").run()
    at.text_input(key="w_descriptor_file").input(str(path)).run()
    assert_clean(at)
    assert any("demo-export descriptors ready: 180 × 2048" in s.value for s in at.success)
    at = page(at, "places")
    assert_clean(at)
    value = database_queries(demo)  # snow queries: the traversals' own order
    ov = overview(fit_retrieval(demo_pixels, value, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(3, 5))),
                  demo_pixels)
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    at = page(at, "evaluation")
    assert_clean(at)
    assert any("descriptor: demo-export" in c.value for c in at.caption)  # the protocol's settings name it


def test_a_changed_descriptor_file_is_read_again(layouts, dq, dq_effnet, tmp_path):
    path = tmp_path / "mine.npz"
    write_descriptor_file(path, dq_effnet, dq.image_paths, dq.root)
    at = opened(layouts["database-queries"], path)
    assert_clean(at)
    at = page(at, "evaluation")
    first = at.dataframe[0].value
    rng = np.random.default_rng(0)
    write_descriptor_file(path, rng.standard_normal(dq_effnet.shape).astype(np.float32), dq.image_paths, dq.root)
    at = page(at, "evaluation")  # no cache cleared: the file's size/time and content hash key every result
    assert_clean(at)
    assert not first.equals(at.dataframe[0].value)


def test_a_radius_change_rebuilds_the_ground_truth(layouts, npz, dq_effnet):
    at = opened(layouts["database-queries"], npz)
    at.number_input(key="w_radius").set_value(15.0).run()
    assert_clean(at)
    assert at.query_params["radius"] == "15.0"
    assert any("within 15 m" in c.value for c in at.caption)
    at = page(at, "evaluation")
    assert_clean(at)
    ds15 = open_dataset(layouts["database-queries"], radius=15.0)
    ev = evaluate_retrieval(ds15, dq_effnet, metric=places().metric)
    rows = at.dataframe[0].value
    assert rows["R@1"].tolist() == pytest.approx([r["R@1"] for r in evaluation_rows(ev)])
    assert any("ground truth: within 15 m" in c.value for c in at.caption)


@pytest.mark.parametrize("layout, says", [
    ("vpr-bench", "listed in ground_truth_new.npy"),
    ("traversal-positions", "within 25 m"),
    ("manifest", "the same place id"),
])
def test_every_layout_opens_with_its_ground_truth(layouts, layout, says):
    at = opened(layouts[layout], descriptor="pixels")
    assert_clean(at)
    assert any(says in c.value for c in at.caption), [c.value for c in at.caption]
    for name in ("places", "inspector", "evaluation"):
        page(at, name)
        assert_clean(at)
    page(at, "inspector")
    name = {"vpr-bench": "0.jpg", "traversal-positions": "night_right · frame 0", "manifest": "Image000.jpg"}[layout]
    assert f"query 0: {name}" in image_captions(at)  # images named by file, or by traversal and frame


def test_a_big_protocol_waits_for_run(layouts, npz, monkeypatch):
    from vpr_explorer.views import numbers

    monkeypatch.setattr(numbers, "AUTO_RUN_PAIRS", 1000)  # GardensPoint's 200 × 200 counts as big
    at = page(opened(layouts["database-queries"], npz), "evaluation")
    assert_clean(at)
    assert not at.dataframe and any("does not start by itself" in i.value for i in at.info)
    at.button(key="w_run").click().run()
    assert_clean(at)
    assert at.dataframe and at.dataframe[0].value["method"].tolist()[0] == "image-level baseline"
    page(at, "places")
    at = page(at, "evaluation")  # in memory now: shown at once
    assert at.dataframe


def test_a_named_layout_is_used_and_a_wrong_one_refused(layouts):
    at = opened(layouts["database-queries"], descriptor="pixels")
    at.selectbox(key="w_layout").set_value("vpr-bench").run()
    assert_clean(at, errors=True)
    assert "VPR-Bench needs ref/, query/ and ground_truth_new.npy" in errors(at)
    assert at.session_state["view"].layout == "auto"  # the previous layout is kept
    at.selectbox(key="w_layout").set_value("database-queries").run()
    assert_clean(at)
    assert at.query_params["layout"] == "database-queries"


def test_vpr_explorer_app_starts_on_the_layout_radius_and_file_given(layouts, npz, monkeypatch):
    from vpr_explorer.app.launch import plan

    launch = plan(dataset=str(layouts["database-queries"]), layout="database-queries", radius=30.0, descriptors=npz)
    assert "layout=database-queries" in launch.url and "radius=30" in launch.url
    for name, value in launch.env.items():
        monkeypatch.setenv(name, value)
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    assert_clean(at)
    assert at.selectbox(key="w_layout").value == "database-queries" and at.number_input(key="w_radius").value == 30
    assert any("within 30 m" in c.value for c in at.caption)
    assert any("effnet_gp descriptors ready" in s.value for s in at.success)


@pytest.mark.parametrize("options, says", [
    (dict(layout="bogus"), "--layout bogus: choose one of auto, traversals"),
    (dict(radius=-1.0), "--radius -1: must be a positive distance in metres"),
    (dict(dataset=None, radius=30.0), "--radius 30.0: give the --dataset it applies to too"),
])
def test_bad_layout_and_radius_options_are_refused(layouts, options, says):
    from vpr_explorer.app.launch import plan
    from vpr_explorer.errors import VPRInputError

    with pytest.raises(VPRInputError, match=says.replace("(", r"\(").replace(".", r"\.")):
        plan(**{"dataset": str(layouts["database-queries"]), **options})


# --------------------------------------------------------------------------- bad input


def test_a_descriptor_path_that_does_not_exist_is_an_error(layouts, tmp_path):
    missing = tmp_path / "nope.npz"
    at = opened(layouts["database-queries"], missing)  # a link naming it
    assert_clean(at, errors=True)
    assert f"descriptor file {missing}: no such file" in errors(at)
    page(at, "places")
    assert_clean(at, errors=True)
    assert "no such file" in errors(at) and "**Dataset** page" in errors(at)

    at = opened(layouts["database-queries"])  # typed in the box: refused, the previous descriptor kept
    at.radio(key="w_descriptor").set_value("__file__").run()
    at.text_input(key="w_descriptor_file").input(str(missing)).run()
    assert_clean(at, errors=True)
    assert "no such file" in errors(at)
    assert at.session_state["view"].descriptors is None and at.session_state["view"].descriptor == "pixels"
    assert at.text_input(key="w_descriptor_file").value == str(missing)  # kept in the box, to be corrected


@pytest.mark.parametrize("fault, says", [
    ("missing", "10 of the dataset's 400 images have no descriptor in the file"),
    ("nan", "1 are NaN or infinite"),
    ("zero", "zero"),
])
def test_a_bad_descriptor_file_is_refused_with_the_librarys_message(layouts, dq, dq_effnet, tmp_path, fault, says):
    d, paths = dq_effnet.copy(), dq.image_paths
    if fault == "missing":
        d, paths = d[:390], paths[:390]
    else:
        d[3] = np.nan if fault == "nan" else 0.0
    path = tmp_path / f"{fault}.npz"
    write_descriptor_file(path, d, paths, dq.root)
    at = opened(layouts["database-queries"], path)
    assert_clean(at, errors=True)
    assert says in errors(at) and str(path) in errors(at)
    if fault == "missing":
        assert "queries/@501900.00@6960000.00" in errors(at)  # the missing images are listed
    for name in ("places", "inspector", "evaluation"):
        page(at, name)
        assert_clean(at, errors=True)
        assert str(path) in errors(at), name


@pytest.mark.parametrize("name, value, says", [
    ("radius", "-1", "radius='-1': must be a positive distance in metres, e.g. 25; using the field's 25 m"),
    ("layout", "bogus", "layout='bogus': choose one of auto, traversals"),
    ("geometry", "spiral", "geometry='spiral': choose frames or route or lattice"),
    ("group_m", "nan", "group_m='nan': must be a positive distance in metres"),
    ("step_m", "10", "step_m='10': step=10 m < group=25 m"),
])
def test_bad_link_parameters_are_ignored_with_a_warning_naming_them(layouts, npz, name, value, says):
    at = opened(layouts["database-queries"], npz, **{name: value})
    assert_clean(at)
    warnings = " ".join(w.value for w in at.sidebar.warning)
    assert says in warnings, warnings
    page(at, "places")
    assert_clean(at)
    assert metric(at, "places") == "20"  # the defaults were used instead


def test_a_geometry_the_dataset_does_not_offer_falls_back_with_a_warning(layouts):
    at = opened(layouts["vpr-bench"], descriptor="pixels", geometry="lattice")  # no positions: frames only
    assert_clean(at)
    assert any("offers frames (its layout has no positions)" in w.value for w in at.warning)
    assert "geometry" not in at.query_params
    page(at, "places")
    assert_clean(at)
    assert at.slider(key="w_group").value == 3
    assert any("no positions: there is no map" in i.value for i in at.info)


# --------------------------------------------------------------------------- places and the map


def test_places_in_metres_are_the_librarys_and_the_map_draws_them(layouts, npz, dq, dq_effnet):
    at = page(opened(layouts["database-queries"], npz), "places")
    assert_clean(at)
    assert at.radio(key="w_geometry").value == "lattice"
    f = fit_retrieval(dq_effnet, dq, places())
    ov = overview(f, dq_effnet)
    assert metric(at, "places") == str(f.n_places) == "20"
    assert metric(at, "database images per place") == "3"
    assert metric(at, "place-level R@1") == f"{ov.recall1['place-baseline']:.0%}"
    assert metric(at, "margin, weighted θ R@1") == f"{ov.recall1['margin-weighted']:.0%}"
    np.testing.assert_allclose(trace(figure(at, "theta_hist"), "θ_p weighted")["x"], f.model.theta["weighted"])

    spec = figure(at, "layout_map")
    origin = np.array([500_000.0, 6_960_000.0])
    grey = trace(spec, "database, between places")
    coloured = trace(spec, "database places")
    np.testing.assert_allclose(grey["x"] + origin[0], dq.database_xy[f.database_place < 0, 0])
    np.testing.assert_allclose(coloured["x"] + origin[0], dq.database_xy[f.database_place >= 0, 0])
    assert list(coloured["text"]) == [f"P{p}" for p in f.database_place[f.database_place >= 0]]
    assert len(trace(spec, "queries")["x"]) == 200
    selected = trace(spec, "selected query")
    assert selected["customdata"][0] == 0 and selected["x"][0] + origin[0] == dq.query_xy[0, 0]
    ring = trace(spec, "radius")
    dist = np.hypot(ring["x"] - selected["x"][0], ring["y"] - selected["y"][0])
    np.testing.assert_allclose(dist, 25.0)
    np.testing.assert_allclose(trace(spec, "positives")["x"] + origin[0],
                               dq.database_xy[dq.ground_truth.positives(0), 0])
    dec = explain_query(f, dq_effnet, 0)
    cands = set(trace(spec, "candidate places")["text"])
    assert cands == {f"P{p}" for p in np.argsort(-dec.raw, kind="stable")[:5]}
    assert spec["layout"]["yaxis"]["scaleanchor"] == "x"  # one metre is one metre both ways


def test_regrouping_in_metres_recomputes_and_goes_into_the_url(layouts, npz, dq, dq_effnet):
    at = page(opened(layouts["database-queries"], npz), "places")
    at.number_input(key="w_step_m").set_value(50.0).run()
    at.number_input(key="w_group_m").set_value(35.0).run()
    assert_clean(at)
    assert at.query_params["group_m"] == "35.0" and at.query_params["step_m"] == "50.0"
    f = fit_retrieval(dq_effnet, dq, places(35.0, 50.0))
    ov = overview(f, dq_effnet)
    assert metric(at, "places") == str(f.n_places) == "40"
    assert metric(at, "database images per place") == "4"
    assert metric(at, "margin, weighted θ R@1") == f"{ov.recall1['margin-weighted']:.0%}"
    at.radio(key="w_geometry").set_value("route").run()  # metres along the listed database: the same line here
    assert_clean(at)
    assert at.query_params["geometry"] == "route"
    assert metric(at, "places") == str(fit_retrieval(dq_effnet, dq, places(35.0, 50.0, PlaceGeometry.ROUTE)).n_places)
    at.radio(key="w_geometry").set_value("frames").run()  # group/step count database images
    assert_clean(at)
    assert at.slider(key="w_group").value == 3 and at.slider(key="w_step").value == 10
    assert metric(at, "places") == "20"


def test_a_group_raised_above_step_is_refused_with_a_way_out(layouts, npz):
    at = page(opened(layouts["database-queries"], npz, step_m=120), "places")
    at.number_input(key="w_group_m").set_value(150.0).run()  # above step 120 m in the stride reading
    assert_clean(at, errors=True)
    assert "places would overlap" in errors(at) and at.number_input(key="w_group_m").value == 25.0
    fix = at.button(key="w_fix_overlap")
    assert "group 150 m, step 150 m" in fix.label
    fix.click().run()
    assert_clean(at)
    assert at.number_input(key="w_group_m").value == 150.0 and at.number_input(key="w_step_m").value == 150.0
    assert at.query_params["group_m"] == "150.0" and at.query_params["step_m"] == "150.0"


def test_a_click_on_a_query_selects_it(layouts, npz, dq):
    at = page(opened(layouts["database-queries"], npz), "places")
    at.number_input(key="w_map_query").set_value(42).run()
    assert_clean(at)
    assert trace(figure(at, "layout_map"), "selected query")["customdata"][0] == 42
    assert at.query_params["frame"] == "42"
    assert any(query_label(dq, 42) in md.value for md in at.markdown)
    at.button(key="w_map_inspect").click().run()
    assert_clean(at)
    assert at.title[0].value == "Query inspector" and at.number_input(key="w_frame_number").value == 42


# --------------------------------------------------------------------------- thresholds


def test_the_thresholds_page_shows_the_librarys_place_detail(layouts, npz, dq, dq_effnet):
    at = page(opened(layouts["database-queries"], npz, place=7), "thresholds")
    assert_clean(at)
    f = fit_retrieval(dq_effnet, dq, places())
    d = place_detail(f, dq_effnet, 7)
    assert len(d.query_images) and set(d.query_images - dq.n_database) == {
        q for q in range(dq.n_queries) if f.right_places([q])[0, 7]}
    spec = figure(at, "mixture")
    assert trace(spec, "θ_p weighted")["x"][0] == pytest.approx(f.model.theta["weighted"][7])
    assert trace(spec, "global θ, automatic")["x"][0] == pytest.approx(f.model.auto)
    raw = trace(spec, "query_raw")
    np.testing.assert_array_equal(raw["customdata"], d.query_images)
    np.testing.assert_allclose(raw["x"], d.query_raw)
    for label, value in (("negative scores ≥ θ_p weighted", d.share_negatives_above(d.theta["weighted"])),
                         ("same-place scores < θ_p weighted", d.share_positives_below(d.theta["weighted"])),
                         ("own queries dropped at θ_p(k=0)", d.share_queries_below(d.theta["weighted"]))):
        assert metric(at, label) == ("—" if np.isnan(value) else f"{value:.0%}"), label
    assert any(f"**P7**: {len(d.images)} database images and {len(d.query_images)} queries" in md.value
               for md in at.markdown)
    captions = image_captions(at)  # the file names ("@east@north@…@.jpg") would be cut off: the indices instead
    assert captions[:len(d.images)] == [f"database image {i}" for i in d.images]
    assert captions[len(d.images):] == [f"query {i - dq.n_database} (raw_p {r:.3f})"
                                        for i, r in zip(d.query_images, d.query_raw)]


def test_a_place_without_queries_shows_dashes(data_root, tmp_path):
    root = unknown_layout(tmp_path / "open_set", data_root / "GardensPointWalking", range(150, 200))
    at = page(opened(root, descriptor="pixels"), "thresholds")
    assert_clean(at)
    ds = open_dataset(root)
    f = fit_retrieval(np.asarray(dataset_descriptors(ds, "pixels")), ds, places())
    lonely = next(p for p in range(f.n_places) if not len(place_queries(f, p)))  # its queries were moved away
    at.selectbox(key="w_place").set_value(lonely).run()
    assert_clean(at)
    assert metric(at, "own queries dropped at θ_p(k=0)") == "—"
    assert any(f"**P{lonely}**" in md.value and "and 0 queries" in md.value for md in at.markdown)


# --------------------------------------------------------------------------- query inspector


def test_the_inspector_opens_a_rejected_query_with_its_right_place(layouts, npz, dq, dq_effnet):
    at = page(opened(layouts["database-queries"], npz), "inspector")
    assert_clean(at)
    at.button(key="w_find_next").click().run()
    assert_clean(at)
    f = fit_retrieval(dq_effnet, dq, places())
    found, _ = find_query(f, dq_effnet, after=0, kind="rejected", method="margin-weighted")
    assert at.number_input(key="w_frame_number").value == found == at.slider(key="w_frame").value
    dec = explain_query(f, dq_effnet, found)
    assert dec.answer("margin-weighted") == -1
    right = f.right_places([found])[0]
    text = " ".join(md.value for md in at.markdown)
    assert f"**Right place(s):** {', '.join(f'P{p}' for p in np.flatnonzero(right))}" in text
    assert "margin, weighted θ**: rejected: the best place" in text
    assert f"query {found}: {query_label(dq, found)}" in image_captions(at)
    positives = [Path(dq.database_paths[i]).name for i in dq.ground_truth.positives(found)]
    assert any(all(p in c.value for p in positives) for c in at.caption)


def test_the_inspector_finds_a_query_by_its_file_name(layouts, npz, dq):
    at = page(opened(layouts["database-queries"], npz), "inspector")
    at.text_input(key="w_query_name").input(Path(dq.query_paths[17]).name).run()
    assert_clean(at)
    assert at.number_input(key="w_frame_number").value == 17
    at.text_input(key="w_query_name").input("no-such-image.jpg").run()
    assert_clean(at, errors=True)
    assert "query file name 'no-such-image.jpg': no query image" in errors(at)


def test_a_query_whose_right_images_lie_between_places_is_not_scored(layouts, npz, dq, dq_effnet):
    f = fit_retrieval(dq_effnet, dq, places())
    assert f.query_status(5) == "between places"  # right: frames 3..7, places hold frames 0-2, 10-12, …
    at = page(opened(layouts["database-queries"], npz, frame=5), "inspector")
    assert_clean(at)
    text = " ".join(md.value for md in at.markdown)
    assert "**Its 5 right database image(s) lie between places**" in text and "**not scored**" in text
    assert "not in the database" not in text and "(not scored: its right database images lie between places)" in text


def unknown_layout(root: Path, gp: Path, far: range) -> Path:
    """GardensPoint database/queries where the queries in ``far`` were taken 5 km away: unknown places."""
    for side, trav in (("database", "day_right"), ("queries", "night_right")):
        for f in range(200):
            north = 6_960_000.0 + (5_000.0 if side == "queries" and f in far else 0.0)
            dst = root / side / utm_name(500_000 + 10.0 * f, north, f)
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to((gp / trav / f"Image{f:03d}.jpg").resolve())
    return root


def test_an_unknown_place_query_is_named_so_and_counted_apart(data_root, gp_effnet, tmp_path):
    root = unknown_layout(tmp_path / "open_set", data_root / "GardensPointWalking", range(150, 200))
    ds = open_dataset(root)
    d = np.asarray(dataset_descriptors(ds, "efficientnet-lite0"))
    path = tmp_path / "effnet_open.npz"
    write_descriptor_file(path, d, ds.image_paths, ds.root)
    at = page(opened(root, path, frame=160), "inspector")
    assert_clean(at)
    text = " ".join(md.value for md in at.markdown)
    assert "**Unknown-place query:** no database image is right for it (within 25 m)" in text
    assert "accepting it is a false positive" in text
    dec = explain_query(fit_retrieval(d, ds, places()), d, 160)
    for key in ("place-baseline", "margin-weighted"):
        if dec.answer(key) >= 0:
            assert "an unknown-place query accepted: a false positive" in text
    at = page(at, "places")
    assert_clean(at)
    ov = overview(fit_retrieval(d, ds, places()), d)
    assert ov.n_unknown == 50 and metric(at, "unknown rejected") == f"{ov.unknown_rejected['margin-weighted']:.0%}"
    at = page(at, "evaluation")
    assert_clean(at)
    assert any("**50 with no right database image**" in c.value for c in at.caption)
    ev = evaluate_retrieval(ds, d, metric=places().metric)
    rows = at.dataframe[0].value
    want = evaluation_rows(ev)
    assert rows["unknown rejected"].tolist() == pytest.approx([r.get("unknown rejected") for r in want], nan_ok=True)
    assert rows["R@1"].tolist() == pytest.approx([r["R@1"] for r in want])


# --------------------------------------------------------------------------- evaluation


def test_the_evaluation_page_runs_the_database_queries_protocol(layouts, npz, dq, dq_effnet):
    at = page(opened(layouts["database-queries"], npz), "evaluation")
    assert_clean(at)
    ev = evaluate_retrieval(dq, dq_effnet, metric=places().metric)
    rows = at.dataframe[0].value
    want = evaluation_rows(ev)
    assert rows["method"].tolist() == [r["method"] for r in want]
    for k in ev.ks:
        assert rows[f"R@{k}"].tolist() == pytest.approx([r[f"R@{k}"] for r in want])
    caption = " ".join(c.value for c in at.caption)
    assert "ground truth: within 25 m" in caption and "**0 with no right database image**" in caption
    bars = trace(figure(at, "recall"), "R@1")
    np.testing.assert_allclose(bars["y"], [r.recall[1][0] for r in ev.rows])


def test_the_protocols_of_aligned_traversals_are_refused_by_name(layouts, npz, dq, dq_effnet):
    from vpr_explorer.protocols.evaluation import PROTOCOL_LABELS, Protocol

    at = page(opened(layouts["database-queries"], npz, eval_protocol="paper", eval_runs=3), "evaluation")
    assert_clean(at)
    said = [w.value for w in at.warning]
    assert any("eval_protocol='paper': the random split needs aligned traversals ('database-queries' is read in "
               "the database-queries layout); using the default (database-queries)" in w for w in said), said
    assert any(w.startswith("eval_runs='3': applies to aligned traversals") for w in said), said
    assert at.radio(key="w_protocol").options == [PROTOCOL_LABELS[Protocol.DATABASE]]
    assert at.radio(key="w_protocol").value == "database-queries"
    assert at.query_params["eval_protocol"] == "database-queries" and "eval_runs" not in at.query_params
    ev = evaluate_retrieval(dq, dq_effnet, metric=places().metric)
    assert at.dataframe[0].value["R@1"].tolist() == pytest.approx([r["R@1"] for r in evaluation_rows(ev)])
    at = page(opened(layouts["database-queries"], npz, eval_protocol="traversal"), "evaluation")  # the same protocol
    assert_clean(at)
    assert not any("eval_protocol" in w.value for w in at.warning)
    assert at.radio(key="w_protocol").value == "database-queries"


# --------------------------------------------------------------------------- the traversal pages' fixes


def test_the_traversal_inspector_has_a_frame_entry_and_names_images_by_frame(demo, demo_pixels):
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    at = page(at, "inspector")
    at.number_input(key="w_frame_number").set_value(31).run()
    assert_clean(at)
    assert at.slider(key="w_frame").value == 31 and at.query_params["frame"] == "31"
    assert "query 31: snow · frame 31" in image_captions(at)
    value = database_queries(demo)  # snow queries, day + night database: the traversals' own order
    answer = image_answer(value, demo_pixels, 31)
    assert database_label(value, answer.image) in ("day · frame 31", "night · frame 31")  # the same spot
    text = " ".join(md.value for md in at.markdown) + " ".join(c.value for c in at.caption)
    assert f"its most similar database image is {database_label(value, answer.image)}" in text
    assert "Right database images: day · frame 31, night · frame 31." in text
    assert "accepted as image" not in text


def test_the_traversal_places_page_offers_to_move_step_along():
    at = page(AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run(), "places")
    at.slider(key="w_group").set_value(8).run()  # step 5 < group 8 in the stride reading
    assert_clean(at, errors=True)
    assert "places would overlap" in errors(at) and at.slider(key="w_group").value == 3
    at.button(key="w_fix_overlap").click().run()
    assert_clean(at)
    assert at.slider(key="w_group").value == 8 and at.slider(key="w_step").value == 8
    assert metric(at, "places") == str(60 // 8)


def test_frames_places_of_a_layout_count_database_images(layouts, dq_effnet, dq, npz):
    at = page(opened(layouts["database-queries"], npz, geometry="frames", group=2, step=5), "places")
    assert_clean(at)
    f = fit_retrieval(dq_effnet, dq, RetrievalPlaces(PlaceGeometry.FRAMES, spec=PlaceSpec(2, 5)))
    assert metric(at, "places") == str(f.n_places) == "40"
    assert metric(at, "database images per place") == "2"
