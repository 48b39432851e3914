"""Group/step sweeps (``vpr_explorer.protocols.sweep``, ``vpr-explorer sweep``) on GardensPoint's pixel descriptors.

Every cell of a small real sweep is checked against a separate evaluation of the same
settings (``pipeline.evaluate_dataset``, what ``vpr-explorer evaluate`` runs; on a
database/queries layout ``pipeline.evaluate_retrieval``): the numbers must be equal, not
close. Then the empty cells and their reasons, bad settings, the cache and the places the
two readings share, the CSV/JSON columns, the heatmap's click data, and the command's exit
codes.
"""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest

from vpr_explorer import pipeline
from vpr_explorer.cli import main
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import evaluate_dataset, evaluate_retrieval, open_dataset
from vpr_explorer.method.places import MetricPlaceSpec, PlaceSpec
from vpr_explorer.protocols import paired
from vpr_explorer.protocols.shared_scores import SharedScores
from vpr_explorer.protocols.sweep import (
    SPREAD_COLUMNS,
    Metric,
    SweepCache,
    SweepSpec,
    colour_range,
    scale_note,
    selected_cell,
    sweep,
    sweep_cost,
    sweep_figure,
    table,
)

pytestmark = pytest.mark.realdata

RUNS = 2


@pytest.fixture(scope="module")
def paper_sweep(gardens_point, gp_pixels):
    """Paper protocol, groups 2 3 × steps 2 5, both readings, 2 runs, with precision–recall."""
    spec = SweepSpec(groups=(3, 2), steps=(5, 2), protocol="paper", runs=RUNS)
    seen = []
    result = sweep(gardens_point, gp_pixels, spec, pipeline, descriptor="pixels",
                   progress=lambda done, total, msg: seen.append((done, total, msg)))
    return result, seen


def _separate(data_root, spec: PlaceSpec, protocol: str, **options):
    return evaluate_dataset(data_root / "GardensPointWalking", spec, "pixels", protocol, pr=True, **options)


def _everything(ev) -> dict:
    """An evaluation's every number, setting, note and curve (NaN as ``None``), all but its time."""
    return {k: v for k, v in ev.to_dict().items() if k != "seconds"}


def test_every_cell_equals_a_separate_evaluation(paper_sweep, data_root):
    result, seen = paper_sweep
    assert result.spec.groups == (2, 3) and result.spec.steps == (2, 5)  # sorted
    assert [c.spec for c in result.cells] == [(g, s, r) for r in ("stride", "skip") for g in (2, 3) for s in (2, 5)]
    assert [d for d, _, _ in seen] == list(range(1, 9)) and all(t == 8 for _, t, _ in seen)
    assert seen[0][2] == "group 2, step 2 (stride)"
    checked = 0
    for c in result.cells:
        if c.empty:
            continue
        ev = _separate(data_root, PlaceSpec(c.group, c.step, c.reading), "paper", runs=RUNS)
        base = ev.row("place-baseline").recall[1][0]
        assert c.r1 == base
        assert c.gain == ev.row("margin-weighted").recall[1][0] - base
        assert c.auc == next(r.auc for r in ev.pr if r.key == "margin-weighted")
        assert math.isnan(c.rejection) and "no unknown places" in c.missing["rejection"]
        assert c.evaluation.same_numbers(ev)
        assert _everything(c.evaluation) == _everything(ev)  # settings restated for the shared cell too
        assert c.n_places == int(ev.settings["places"].split()[0])
        checked += 1
    assert checked == 7


def test_open_set_rejection_at_k_equals_a_separate_evaluation(gardens_point, gp_pixels, data_root):
    spec = SweepSpec(groups=(3,), steps=(5, 10), readings=("stride",), protocol="open-set", runs=RUNS, k=1.25,
                     k_grid=(0.0, 1.0))
    assert spec.k_grid == (0.0, 1.0, 1.25)  # the reported k joins the grid
    result = sweep(gardens_point, gp_pixels, spec, pipeline, descriptor="pixels")
    for c in result.cells:
        ev = _separate(data_root, PlaceSpec(c.group, c.step), "open-set", runs=RUNS, k_grid=[0.0, 1.0, 1.25])
        row = next(t for t in ev.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "margin" and t.param == 1.25)
        assert c.rejection == row.unknown_rejection[0]
        assert c.stats["rejection"] == paired.summary(row.per_split["unknown_rejection"])
        assert c.stats["rejection"].mean == c.rejection and c.stats["rejection"].n == RUNS
        assert c.r1 == ev.row("place-baseline").recall[1][0]
        assert c.auc == next(r.auc for r in ev.pr if r.key == "margin-weighted")
        assert _everything(c.evaluation) == _everything(ev)
    # a higher k rejects at least as many unknown places (same splits, larger thresholds)
    low = sweep(gardens_point, gp_pixels, SweepSpec(groups=(3,), steps=(5, 10), readings=("stride",),
                                                     protocol="open-set", runs=RUNS, k=0.0, k_grid=(0.0, 1.0)),
                pipeline)
    assert all(h.rejection >= lo.rejection for h, lo in zip(result.cells, low.cells))
    # R@1 and the rejection (both % of queries) share one colour scale, spanning both grids
    span = colour_range(result, "r1")
    assert span == colour_range(result, "rejection")
    values = [100 * v for c in result.cells for v in (c.r1, c.rejection)]
    assert span == (min(values), max(values))
    for metric in ("r1", "rejection"):
        heat = next(t for t in sweep_figure(result, metric, "stride").data if t.meta == "values")
        assert (heat.zmin, heat.zmax) == span
    assert "the same for R@1 and the rejection" in scale_note(result, "rejection")


def test_traversal_cells_and_method(gardens_point, gp_pixels, data_root):
    spec = SweepSpec(groups=(2,), steps=(4,), readings=("skip",), protocol="traversal", method="raw-simple",
                     tolerance=1)
    c = sweep(gardens_point, gp_pixels, spec, pipeline, descriptor="pixels").cells[0]
    ev = _separate(data_root, PlaceSpec(2, 4, "skip"), "traversal", tolerance=1)
    assert c.gain == ev.row("raw-simple").recall[1][0] - ev.row("place-baseline").recall[1][0]
    assert c.auc == next(r.auc for r in ev.pr if r.key == "raw-simple")
    assert _everything(c.evaluation) == _everything(ev)
    # one deterministic run: its numbers, no interval, said as one run
    assert c.n_splits == 1 and c.stats["r1"].note == "one run" and math.isnan(c.stats["r1"].std)
    assert c.stats["gain"].tag == "one run" and math.isnan(c.stats["gain"].p)
    assert c.spread("r1") == f"{100 * c.r1:.1f} (one run)"


def test_cells_state_their_spread_over_splits(paper_sweep):
    """R@1: mean ± std (ddof 1) and the t interval of the baseline's per-split R@1; the gain: the paired
    comparison of the method and the baseline on the cell's splits; the AUC: one pooled number."""
    result, _ = paper_sweep
    for c in result.cells:
        if c.empty:
            assert c.stats == {} and c.n_splits == 0 and c.spread("r1") == ""
            continue
        base = np.asarray(c.evaluation.row("place-baseline").per_split["recall@1"])
        method = np.asarray(c.evaluation.row("margin-weighted").per_split["recall@1"])
        assert len(base) == RUNS and c.n_splits == RUNS
        r1 = c.stats["r1"]
        assert r1.mean == c.r1 and r1.std == pytest.approx(np.std(base, ddof=1), abs=1e-15)
        half = 12.706204736174698 * r1.std / math.sqrt(2)  # t₀.₉₇₅ with 1 degree of freedom
        assert (r1.low, r1.high) == pytest.approx((c.r1 - half, c.r1 + half), abs=1e-12)
        gain = c.stats["gain"]
        assert gain.paired and gain.mean == pytest.approx(c.gain, abs=1e-15)
        d = method - base
        if np.ptp(d) > 1e-12:
            assert gain.std == pytest.approx(np.std(d, ddof=1)) and 0 < gain.p <= 1
        else:
            assert gain.identical or gain.p == 0.0
        assert c.stats["auc"].mean == c.auc and c.stats["auc"].note == "pooled over the splits"
        assert "rejection" not in c.stats  # a closed set
        assert c.spread("r1").endswith(f", {RUNS} splits") and " ± " in c.spread("r1")


def test_heatmaps_share_one_colour_scale_and_hover_the_spread(paper_sweep):
    result, _ = paper_sweep
    for metric in ("r1", "gain", "auc"):
        span = colour_range(result, metric)
        figures = [sweep_figure(result, metric, r) for r in ("stride", "skip")]
        heats = [next(t for t in f.data if t.meta == "values") for f in figures]
        assert all((h.zmin, h.zmax) == pytest.approx(span) for h in heats), metric  # both readings: one scale
        z = np.concatenate([np.asarray(h.z, dtype=float).ravel() for h in heats])
        z = z[np.isfinite(z)]
        if metric == "gain":
            assert span == (-max(np.abs(z).max(), 1.0), max(np.abs(z).max(), 1.0))
        else:
            assert span == pytest.approx((z.min(), z.max()))
        assert "both readings share it" in scale_note(result, metric)
    cells = next(t for t in sweep_figure(result, "r1", "stride").data if t.meta == "cells")
    c = result.cell(2, 5, "stride")
    assert any(c.spread("r1") in text for text in cells.text)
    gain = next(t for t in sweep_figure(result, "gain", "stride").data if t.meta == "cells")
    assert any("paired over 2 splits" in text or "identical on every split" in text or "no spread" in text
               or "the same difference" in text for text in gain.text)


def test_empty_cells_say_why(paper_sweep, gardens_point, gp_pixels):
    result, _ = paper_sweep
    overlap = result.cell(3, 2, "stride")
    assert overlap.empty and "step=2 < group=3" in overlap.empty and "overlap" in overlap.empty
    assert overlap.n_places == 0 and math.isnan(overlap.r1) and overlap.evaluation is None
    assert overlap.why(Metric.AUC) == overlap.empty
    assert "—" in table(result, "r1", "stride").splitlines()[-1]  # group 3 row, step 2 column
    # a step that leaves one place, and a protocol that refuses the places (one image per place)
    spec = SweepSpec(groups=(1, 150), steps=(160,), readings=("stride",), protocol="paper", runs=1)
    few = sweep(gardens_point, gp_pixels, spec, pipeline).cells
    assert "leaves 1 place(s)" in few[1].empty and "lower group or step" in few[1].empty
    assert few[0].empty is None  # group 1 step 160: 2 places × 3 images
    assert sweep_cost(gardens_point, spec).valid == 1


def test_readings_share_places_and_cache(paper_sweep, gardens_point, gp_pixels):
    result, _ = paper_sweep
    shared = result.cell(3, 2, "skip")  # skip 3/2 = stride 3/5: period 5, group 3
    first = result.cell(3, 5, "stride")
    assert shared.same_as == (3, 5, "stride") and shared.seconds == 0.0 and first.seconds > 0
    assert shared.r1 == first.r1 and shared.auc == first.auc
    assert shared.evaluation.settings["reading"] == "skip" and "skip reading" in shared.evaluation.settings["places"]
    cache = SweepCache()
    spec = SweepSpec(groups=(2,), steps=(3,), readings=("stride",), protocol="traversal")
    key = "test-key"
    assert sweep_cost(gardens_point, spec, cache=cache, descriptors_key=key).runs == 1
    one = sweep(gardens_point, gp_pixels, spec, pipeline, cache=cache, descriptors_key=key)
    assert sweep_cost(gardens_point, spec, cache=cache, descriptors_key=key).runs == 0
    two = sweep(gardens_point, gp_pixels, spec, pipeline, cache=cache, descriptors_key=key)
    assert two.cells[0].cached and two.cells[0].evaluation is one.cells[0].evaluation
    other = SweepSpec(groups=(2,), steps=(3,), readings=("stride",), protocol="traversal", tolerance=1)
    assert sweep_cost(gardens_point, other, cache=cache, descriptors_key=key).runs == 1  # options are in the key


def test_cells_share_one_set_of_scores(gardens_point, gp_pixels):
    # one float32 similarity and one float64 Gram of all 600 images serve every paper and open-set cell
    shared = SharedScores(gp_pixels)
    spec = SweepSpec(groups=(2, 3), steps=(5,), readings=("stride",), protocol="open-set", runs=1, pr=False)
    result = sweep(gardens_point, gp_pixels, spec, pipeline, descriptor="pixels", shared=shared)
    assert all(c.empty is None for c in result.cells)
    gram = shared.gram()
    assert shared._full is not None and len(gram.images) == 600
    sweep(gardens_point, gp_pixels, SweepSpec(groups=(2, 3), steps=(5,), readings=("stride",),
                                              protocol="paper", runs=1, pr=False), pipeline, shared=shared)
    assert shared.gram() is gram  # built once
    alone = evaluate_dataset(gardens_point.root, PlaceSpec(3, 5), "pixels", "open-set", runs=1)
    assert _everything(result.cells[1].evaluation) == _everything(alone)
    with pytest.raises(VPRInputError, match="shared scores were built from other descriptors"):
        sweep(gardens_point, gp_pixels.copy(), spec, pipeline, shared=shared)


def test_bad_settings_are_refused_by_name(gardens_point, gp_pixels):
    cases = [
        (dict(groups=(), steps=(5,)), "groups: give at least one"),
        (dict(groups=(0, 2), steps=(5,)), "groups=0"),
        (dict(groups=(2,), steps=(2.5,)), "steps=2.5"),
        (dict(groups=(2,), steps=(5,), readings=("diagonal",)), "reading 'diagonal'"),
        (dict(groups=(2,), steps=(5,), readings=()), "readings"),
        (dict(groups=(2,), steps=(5,), protocol="retrieval"), "a sweep runs paper, traversal, open-set, "
                                                               "database-queries"),
        (dict(groups=(2,), steps=(5,), geometry="route"), "geometry route: the paper protocol makes places of"),
        (dict(groups=(0.5,), steps=(5,), protocol="database-queries", geometry="lattice"), None),
        (dict(groups=(0,), steps=(5,), protocol="database-queries", geometry="route"), "groups=0: must be a "
                                                                                         "distance in metres"),
        (dict(groups=(2,), steps=(5,), protocol="database-queries", tolerance=2), "tolerance=2"),
        (dict(groups=(2,), steps=(5,), method="image-baseline"), "method 'image-baseline'"),
        (dict(groups=(2,), steps=(5,), k=float("nan")), "k=nan"),
        (dict(groups=tuple(range(1, 21)), steps=tuple(range(1, 21))), "800 cells: at most 400"),
    ]
    for kwargs, message in cases:
        if message is None:
            assert SweepSpec(**kwargs).groups == (0.5,)  # metres may have a fraction
            continue
        with pytest.raises(VPRInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
            SweepSpec(**kwargs)
    with pytest.raises(VPRInputError, match="runs=0"):
        sweep(gardens_point, gp_pixels, SweepSpec(groups=(2,), steps=(5,), runs=0), pipeline)
    with pytest.raises(VPRInputError, match="599 descriptors for 600 images"):
        sweep(gardens_point, gp_pixels[:599], SweepSpec(groups=(2,), steps=(5,), protocol="traversal"), pipeline)


def test_csv_and_json_carry_every_setting(paper_sweep):
    result, _ = paper_sweep
    rows = list(csv.DictReader(io.StringIO(result.to_csv())))
    assert len(rows) == 8
    for name in ("dataset", "descriptor", "protocol", "method", "runs", "seed", "cross_condition", "tolerance",
                 "theta", "pr", "reading", "group", "step", "n_places", "r1", "gain", "rejection", "auc", "empty"):
        assert name in rows[0], name
    assert {r["dataset"] for r in rows} == {"GardensPointWalking"} and {r["descriptor"] for r in rows} == {"pixels"}
    assert {r["protocol"] for r in rows} == {"paper"} and {r["runs"] for r in rows} == {str(RUNS)}
    for name in SPREAD_COLUMNS:
        assert name in rows[0], name
    for row, c in zip(rows, result.cells):
        assert (int(row["group"]), int(row["step"]), row["reading"]) == c.spec
        assert row["r1"] == ("" if c.empty else repr(c.r1))  # repr: the exact float
        if not c.empty:
            assert float(row["auc"]) == c.auc
            assert int(row["n_splits"]) == RUNS and float(row["r1_std"]) == c.stats["r1"].std
            assert (float(row["r1_ci95_low"]), float(row["r1_ci95_high"])) == (c.stats["r1"].low, c.stats["r1"].high)
            assert float(row["gain_ci95_high"]) == c.stats["gain"].high
            gain_p = c.stats["gain"].p
            assert row["gain_p"] == ("" if math.isnan(gain_p) else repr(gain_p))
            assert row["gain_test"] == c.stats["gain"].note
        else:
            assert row["r1_std"] == "" and row["n_splits"] == "0"
    data = json.loads(result.to_json())
    assert data["settings"]["runs"] == RUNS and data["settings"]["descriptor"] == "pixels"
    first = next(c for c in result.cells if not c.empty)
    assert data["cells"][[x.spec for x in result.cells].index(first.spec)]["r1_std"] == first.stats["r1"].std
    assert data["groups"] == [2, 3] and data["readings"] == ["stride", "skip"]
    overlap = next(c for c in data["cells"] if (c["group"], c["step"], c["reading"]) == (3, 2, "stride"))
    assert overlap["r1"] is None and "overlap" in overlap["empty"]
    assert next(c for c in data["cells"] if c["reading"] == "skip" and c["group"] == 3
                and c["step"] == 2)["same_as"] == {"group": 3, "step": 5, "reading": "stride"}


def test_heatmap_cells_carry_their_settings(paper_sweep):
    result, _ = paper_sweep
    fig = sweep_figure(result, "gain", "stride", marked=(2, 5))
    heat = next(t for t in fig.data if t.meta == "values")
    cells = next(t for t in fig.data if t.meta == "cells")
    z = np.asarray(heat.z, dtype=float)
    assert z.shape == (2, 2) and np.isnan(z[1, 0])  # group 3, step 2: overlapping places
    assert z[0, 1] == 100 * result.cell(2, 5, "stride").gain
    assert heat.zmid == 0 and list(heat.x) == ["2", "5"] and list(heat.y) == ["2", "3"]
    assert [list(d) for d in cells.customdata] == [[2, 2, "stride"], [2, 5, "stride"], [3, 5, "stride"]]
    empty = next(t for t in fig.data if t.meta == "empty")
    assert list(empty.x) == ["2"] and list(empty.y) == ["3"] and "overlap" in empty.text[0]
    assert selected_cell({"customdata": [3, 5, "stride"]}) == (3, 5, "stride")
    assert selected_cell({"customdata": {"0": 2, "1": 2, "2": "skip"}}) == (2, 2, "skip")
    assert selected_cell({"x": "5"}) is None and selected_cell({"customdata": [1, 2, "diagonal"]}) is None
    box = fig.layout.shapes[0]
    assert (box.x0, box.x1, box.y0, box.y1) == (0.5, 1.5, -0.5, 0.5)  # step 5 (column 1), group 2 (row 0)


# --------------------------------------------------------------------------- a database/queries layout


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    """GardensPoint written in the field's layouts (``example_layouts``): layout name -> path."""
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("sweep_layouts"))


def _pixels_of(value, gardens_point, gp_pixels):
    """The pixel descriptors of a layout's images (links to GardensPoint's), database rows first."""
    rows = {p.resolve(): i for i, p in enumerate(gardens_point.image_paths)}
    return gp_pixels[[rows[p.resolve()] for p in value.image_paths]]


SETTINGS = {"descriptor": "pixels", "dtype": "float32"}


def test_a_database_queries_layout_sweeps_the_database_queries_protocol(layouts, gardens_point, gp_pixels):
    value = open_dataset(layouts["database-queries"])
    d = _pixels_of(value, gardens_point, gp_pixels)
    spec = SweepSpec(groups=(2, 3), steps=(3, 5), protocol="database-queries")
    assert spec.options() == {"user_theta": None} and spec.settings()["runs"] is None
    result = sweep(value, d, spec, pipeline, descriptor="pixels")
    assert result.cell(2, 3, "skip").same_as == (2, 5, "stride")  # skip 2/3 = stride 2/5
    for c in result.cells:
        assert c.empty is None, c.empty
        ev = evaluate_retrieval(value, d, spec=PlaceSpec(c.group, c.step, c.reading), settings=SETTINGS, pr=True)
        assert _everything(c.evaluation) == _everything(ev)  # the shared cell's settings restated too
        base = ev.row("place-baseline").recall[1][0]
        assert c.r1 == base and c.gain == ev.row("margin-weighted").recall[1][0] - base
        assert c.auc == next(r.auc for r in ev.pr if r.key == "margin-weighted")
        assert c.n_places == int(ev.settings["places"].split()[0])
        assert math.isnan(c.rejection) and "no unknown-place query" in c.missing["rejection"]
    assert sweep_cost(value, spec).pairs == 7 * 200 * 200  # 8 cells, one pair of them shares its places


def test_metres_along_the_route_and_unknown_places(layouts, gardens_point, gp_pixels):
    import dataclasses

    from vpr_explorer.data.groundtruth import GroundTruth

    value = open_dataset(layouts["database-queries"])
    gt = value.ground_truth  # every fourth query's positives left out: an unknown place each
    value = dataclasses.replace(value, ground_truth=GroundTruth.from_lists(
        [[] if q % 4 == 0 else gt.positives(q) for q in range(value.n_queries)], value.n_database, "every fourth out"))
    d = _pixels_of(value, gardens_point, gp_pixels)
    spec = SweepSpec(groups=(20, 25.5), steps=(50,), readings=("stride",), protocol="database-queries",
                     geometry="route", method="raw-weighted")
    result = sweep(value, d, spec, pipeline, descriptor="pixels")
    for c in result.cells:
        ev = evaluate_retrieval(value, d, metric=MetricPlaceSpec(c.group, c.step, c.reading, "route"),
                                settings=SETTINGS, pr=True)
        assert _everything(c.evaluation) == _everything(ev)
        assert c.rejection == ev.row("raw-weighted").unknown_rejection[0] and "rejection" not in c.missing
    assert "group \\ step (m)" in table(result, "r1", "stride")
    fig = sweep_figure(result, "rejection", "stride", marked=(25.5, 50))
    assert fig.layout.xaxis.title.text == "step (m)" and fig.layout.shapes
    cells = next(t for t in fig.data if t.meta == "cells")
    assert [selected_cell({"customdata": list(x)}) for x in cells.customdata] == [(20, 50, "stride"),
                                                                                 (25.5, 50, "stride")]


def test_protocols_and_layouts_a_sweep_refuses_by_name(layouts, gardens_point, gp_pixels):
    value = open_dataset(layouts["vpr-bench"])
    d = _pixels_of(value, gardens_point, gp_pixels)
    for protocol in ("paper", "traversal", "open-set"):
        with pytest.raises(VPRInputError, match=f"protocol {protocol}: it needs aligned traversals.*vpr-bench layout"):
            sweep(value, d, SweepSpec(groups=(2,), steps=(5,), protocol=protocol), pipeline)
    named = open_dataset(layouts["manifest"])
    with pytest.raises(VPRInputError, match="group/step do not apply: the manifest layout .* names its places"):
        sweep_cost(named, SweepSpec(groups=(2,), steps=(5,), protocol="database-queries"))
    with pytest.raises(VPRInputError, match="give 'GardensPointWalking' as its database/queries value"):
        sweep(gardens_point, gp_pixels, SweepSpec(groups=(2,), steps=(5,), protocol="database-queries"), pipeline)


def test_cli_sweep_on_a_database_queries_layout(layouts, gardens_point, gp_pixels, tmp_path, capsys):
    out_json = tmp_path / "sweep.json"
    rc = main(["sweep", "--dataset", str(layouts["vpr-bench"]), "--descriptor", "pixels", "--groups", "2", "3",
               "--steps", "5", "--reading", "stride", "--metric", "r1", "--json", str(out_json)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "vpr-bench: 2 cells, 2 with valid places, 2 protocol runs" in out and "database-queries protocol" in out
    data = json.loads(out_json.read_text())
    assert data["settings"]["protocol"] == "database-queries" and data["settings"]["geometry"] == "frames"
    value = open_dataset(layouts["vpr-bench"])
    ev = evaluate_retrieval(value, _pixels_of(value, gardens_point, gp_pixels), spec=PlaceSpec(3, 5), pr=True)
    assert data["cells"][1]["r1"] == ev.row("place-baseline").recall[1][0]
    for argv, message in ((["--dataset", str(layouts["vpr-bench"]), "--protocol", "paper"], "protocol paper: it "
                           "needs aligned traversals"),
                          (["--dataset", str(layouts["vpr-bench"]), "--runs", "3"], "--runs applies to the paper"),
                          (["--dataset", str(layouts["manifest"])], "group/step do not apply")):
        assert main(["sweep", "--descriptor", "pixels", "--groups", "2", "--steps", "5", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("error: ") and message in err[-1], err


# --------------------------------------------------------------------------- the command


def test_cli_sweep_prints_the_grid_and_writes_files(data_root, tmp_path, capsys):
    out_csv, out_json = tmp_path / "sweep.csv", tmp_path / "sweep.json"
    rc = main(["sweep", "--dataset", str(data_root / "GardensPointWalking"), "--descriptor", "pixels",
               "--groups", "2", "3", "--steps", "2", "5", "--reading", "stride", "--protocol", "traversal",
               "--metric", "r1", "gain", "--csv", str(out_csv), "--json", str(out_json)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "GardensPointWalking: 4 cells, 3 with valid places, 3 protocol runs" in out
    assert "place-level R@1 (%), stride reading" in out and "gain in R@1" in out and "AUC" not in out
    assert "empty: 3/2 stride: step=2 < group=3" in out
    assert "missing: rejection (3 cells)" in out
    rows = list(csv.DictReader(out_csv.open()))
    assert [(r["group"], r["step"], r["reading"]) for r in rows] == [("2", "2", "stride"), ("2", "5", "stride"),
                                                                      ("3", "2", "stride"), ("3", "5", "stride")]
    assert rows[0]["protocol"] == "traversal" and rows[0]["descriptor"] == "pixels" and rows[0]["tolerance"] == "0"
    data = json.loads(out_json.read_text())
    assert data["settings"]["protocol"] == "traversal" and len(data["cells"]) == 4
    ev = evaluate_dataset(data_root / "GardensPointWalking", PlaceSpec(2, 5), "pixels", "traversal", pr=True)
    assert data["cells"][1]["r1"] == ev.row("place-baseline").recall[1][0]


@pytest.mark.parametrize("argv, message", [
    (["--groups", "0", "--steps", "5"], "groups=0"),
    (["--groups", "2", "--steps", "5", "--protocol", "traversal", "--runs", "3"], "--runs applies to the paper"),
    (["--groups", "2", "--steps", "5", "--protocol", "paper", "--k", "1"], "--k applies to the open-set"),
    (["--groups", "2", "--steps", "5", "--runs", "0"], "runs=0"),
    (["--groups", "2", "--steps", "5", "--protocol", "traversal", "--csv", "/nonexistent/dir/s.csv"],
     "--csv /nonexistent/dir/s.csv: cannot write"),
    (["--groups", "2", "--steps", "5", "--geometry", "route"], "--geometry applies to database/queries"),
])
def test_cli_sweep_refuses_bad_input_in_one_line(data_root, capsys, argv, message):
    rc = main(["sweep", "--dataset", str(data_root / "GardensPointWalking"), "--descriptor", "pixels", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err[-1].startswith("error: ") and message in err[-1], err
    assert not any("Traceback" in line for line in err)


def test_cli_sweep_needs_a_grid(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["sweep", "--dataset", "demo", "--steps", "5"])
    assert exc.value.code == 2 and "--groups" in capsys.readouterr().err
