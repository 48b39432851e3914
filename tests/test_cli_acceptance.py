"""``vpr-explorer acceptance``: the real command on real data, its numbers against ``acceptance_report`` itself.

GardensPoint Walking (day_left queries against the day_right database, pixel descriptors) runs
in well under two seconds; the database/queries layout is GardensPoint written by
``data.example_layouts``; bad input runs on the built-in demo route, so those tests need no
data.
"""

import json
import subprocess
import sys

import pytest

from tests.cli_run import assert_one_error_line, refused, run
from tests.images import write_noisy_route
from vpr_explorer.cli import acceptance as cli
from vpr_explorer.cli import main
from vpr_explorer.data.aligned import database_queries
from vpr_explorer.method.places import PlaceSpec, retrieval_places
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.protocols.acceptance import (
    RULES,
    RULES_BY_KEY,
    BenchOptions,
    PlaceScore,
    PlaceSource,
    acceptance_report,
)

GP_PAIR = ("--queries", "day_left", "--database", "day_right")
SEQUENCE_RULES = [r.key for r in RULES if r.needs == "sequence"]


def strict(text: str) -> dict:
    """``json.loads`` that refuses NaN and ±Infinity (what ``allow_nan=False`` never writes)."""
    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def plain(d: dict) -> dict:
    """A ``to_dict`` as JSON reads it back (tuples as lists, int keys as strings)."""
    return json.loads(json.dumps(d, allow_nan=False))


def direct_report(gardens_point, options: BenchOptions, tolerance: int = 2):
    """``acceptance_report`` on GardensPoint day_left against day_right, called as the API documents it."""
    value = database_queries(gardens_point, "day_left", database=["day_right"], tolerance=tolerance)
    labels, _ = retrieval_places(value, PlaceSpec(3, 10))
    return acceptance_report(value, dataset_descriptors(value, "pixels"), labels=labels, options=options)


def table_rows(stdout: str) -> dict[str, str]:
    """Rule key -> its printed table row (rows start with the rule's label; the longest label that fits wins)."""
    rows = {}
    by_length = sorted(RULES, key=lambda rule: -len(rule.label))  # "per-query threshold + graph matcher" first
    for line in stdout.splitlines():
        rule = next((rule for rule in by_length if line.startswith(rule.label + " ")), None)
        if rule is not None and rule.key not in rows:
            rows[rule.key] = line
    return rows


def assert_same_numbers(data: dict, report) -> None:
    """The JSON's closed set, natural open set and notes are the direct report's."""
    want = plain(report.to_dict())
    for part in ("closed_set", "natural_open_set", "natural_open_set_note", "notes"):
        assert data[part] == want[part], part


# --------------------------------------------------------------------------- GardensPoint


def test_gardens_point_table_and_json_are_the_direct_report(gardens_point, tmp_path):
    out = tmp_path / "gp.json"
    r = run("acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
            "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    report = direct_report(gardens_point, BenchOptions())
    data = strict(out.read_text())
    assert_same_numbers(data, report)
    want = {"queries": "day_left", "database": "day_right", "tolerance": 2, "descriptor": "pixels",
            "places": "group-step", "place_score": "best", "authors": False}
    assert {k: data["settings"][k] for k in want} == want
    assert "GardensPointWalking: queries day_left against database day_right (as given)" in r.stdout
    assert "within ±2 frames" in r.stdout
    # a row per rule that ran, holding its closed-set F1 and R@1; SUE is left out with the reason
    rows = table_rows(r.stdout)
    assert set(rows) == set(report.closed.decisions) == set(RULES_BY_KEY) - {"sue"}
    for key, line in rows.items():
        got = data["closed_set"]["rules"][key]
        assert line.split()[-5:-3] == [f"{got['F1']:.1f}", f"{got['recall_at']['1']:.1f}"], line
    assert "sue left out: " in r.stdout and "not metres" in r.stdout
    assert f"wrote {out}" in r.stdout


def test_authors_sets_what_it_says(gardens_point, tmp_path, capsys):
    out = tmp_path / "authors.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR, "--authors",
                 "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert ("--authors: the authors' follow-up choices: discovered places, mean place score, ±2 frames, fan-out 5"
            in stdout)
    assert "places: discovered online from the database; place score: mean" in stdout
    data = strict(out.read_text())
    s = data["settings"]
    assert (s["places"], s["place_score"], s["tolerance"], s["fanout"], s["authors"]) == (
        "discovered", "mean", 2, 5, True)
    assert_same_numbers(data, direct_report(gardens_point, BenchOptions(
        places=PlaceSource.DISCOVERED, place_score=PlaceScore.MEAN, fanout=5), tolerance=2))
    # the same options spelt out give the same numbers
    out2 = tmp_path / "spelt.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
                 "--places", "discovered", "--place-score", "mean", "--tolerance", "2", "--fanout", "5",
                 "--json", str(out2)]) == 0
    capsys.readouterr()
    spelt = strict(out2.read_text())
    assert spelt["closed_set"] == data["closed_set"] and spelt["natural_open_set"] == data["natural_open_set"]


def test_options_reach_the_bench(gardens_point, tmp_path, capsys):
    out = tmp_path / "opts.json"
    args = ["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
            "--rules", "baseline", "seqslam", "per-query-graph", "--tau", "seqslam=0.99", "--tolerance", "1",
            "--group", "2", "--step", "5", "--reference-share", "0.6", "--patch", "10", "--ds", "6", "--fanout", "3",
            "--json", str(out)]
    assert main(args) == 0
    stdout = capsys.readouterr().out
    data = strict(out.read_text())
    value = database_queries(gardens_point, "day_left", database=["day_right"], tolerance=1)
    labels, _ = retrieval_places(value, PlaceSpec(2, 5))
    options = BenchOptions(rules=("baseline", "seqslam", "per-query-graph"), taus={"seqslam": 0.99},
                           reference_share=0.6, patch=10, ds=6, fanout=3)
    assert_same_numbers(data, acceptance_report(value, dataset_descriptors(value, "pixels"), labels=labels,
                                                options=options))
    assert set(data["closed_set"]["rules"]) == {"baseline", "seqslam", "per-query-graph"}
    assert (data["settings"]["fanout"], data["settings"]["patch"], data["settings"]["ds"]) == (3, 10, 6)
    assert data["closed_set"]["rules"]["seqslam"]["tau"] == 0.99
    assert data["closed_set"]["rules"]["seqslam"]["tau_note"] == "given"
    assert data["settings"]["taus"] == {"seqslam": 0.99} and data["settings"]["tolerance"] == 1
    rows = table_rows(stdout)
    assert set(rows) == {"baseline", "seqslam", "per-query-graph"}
    assert "†" not in rows["seqslam"]  # a given τ is no oracle's
    assert "open F1 (60%)" in stdout and "within ±1 frames" in stdout


def test_descriptor_file_rows_move_to_the_value_order(gardens_point, gp_pixels, tmp_path, capsys):
    from vpr_explorer.descriptors.imported import write_descriptor_file

    # day_right (the second traversal) as the database: the file's rows, in the dataset's order, must move
    path = tmp_path / "gp_pix.npz"
    write_descriptor_file(path, gp_pixels, gardens_point.image_paths, gardens_point.root)
    out = tmp_path / "file.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptors", str(path), *GP_PAIR,
                 "--json", str(out)]) == 0
    capsys.readouterr()
    data = strict(out.read_text())
    assert data["settings"]["descriptor"] == "gp_pix"
    assert_same_numbers(data, direct_report(gardens_point, BenchOptions()))


# --------------------------------------------------------------------------- which traversals


def test_default_traversals_are_the_traversal_protocols(capsys):
    assert main(["acceptance", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
                 "--rules", "baseline", "--ds", "4"]) == 0
    stdout = capsys.readouterr().out
    assert "demo: queries snow against database day (default by folder order" in stdout


def test_several_default_database_traversals_keep_the_first(tmp_path, capsys):
    root = write_noisy_route(tmp_path / "route", names=("ref", "map", "query"), frames=30)
    out = tmp_path / "route.json"
    assert main(["acceptance", "--dataset", str(root), "--descriptor", "pixels", "--rules", "baseline", "seqslam",
                 "--ds", "4", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    # folders in name order: map, query, ref; both named database traversals, map the first
    assert "queries query against database map (default, recognised from the traversal names)" in stdout
    assert "database: map, the first of the default database traversals map, ref" in stdout
    data = strict(out.read_text())
    assert data["settings"]["database"] == "map" and data["settings"]["n_database"] == 30
    assert "seqslam" in data["closed_set"]["rules"]  # one route: the sequence rules run


# --------------------------------------------------------------------------- a database/queries layout


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    """GardensPoint in each layout ``example_layouts`` writes: layout name -> path."""
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("acceptance_layouts"))


@pytest.fixture(scope="module")
def database_queries_layout(layouts):
    return layouts["database-queries"]


def test_database_queries_layout_leaves_sequences_and_the_natural_open_set_out(database_queries_layout, tmp_path,
                                                                               capsys):
    out = tmp_path / "dq.json"
    assert main(["acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels",
                 "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    data = strict(out.read_text())
    assert data["settings"]["layout"] == "database-queries" and "tolerance" not in data["settings"]
    for key in SEQUENCE_RULES:
        assert key in data["closed_set"]["left_out"]
        line = next(line for line in stdout.splitlines() if line.startswith(f"{key} left out: "))
        assert "no database route in order" in line
    assert set(table_rows(stdout)) == set(RULES_BY_KEY) - set(SEQUENCE_RULES)  # SUE runs: positions in metres
    assert data["natural_open_set"] is None
    line = next(line for line in stdout.splitlines() if line.startswith("natural open set not run: "))
    assert "not one route in order" in line
    assert "database-queries" in stdout and "database and 200 query images" in stdout


def test_traversal_positions_keep_the_first_default_database_traversal(layouts, tmp_path, capsys):
    import shutil

    # a third traversal folder (day_right's images and positions again, first in name order): by default the
    # loader queries night_right against both others, and the bench keeps the first
    root = tmp_path / "three"
    for name, source in (("another", "day_right"), ("day_right", "day_right"), ("night_right", "night_right")):
        shutil.copytree(layouts["traversal-positions"] / source, root / name, symlinks=True)
    out = tmp_path / "three.json"
    assert main(["acceptance", "--dataset", str(root), "--layout", "traversal-positions", "--descriptor", "pixels",
                 "--rules", "baseline", "seqslam", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "queries night_right against another, day_right (the last traversal against the others)" in stdout
    assert "database: another, the first of the default database traversals another, day_right" in stdout
    data = strict(out.read_text())
    assert (data["settings"]["database"], data["settings"]["queries"]) == (["another"], "night_right")
    assert data["settings"]["n_database"] == 200 and "seqslam" in data["closed_set"]["rules"]
    r = refused(capsys, "acceptance", "--dataset", str(root), "--descriptor", "pixels", "--database", "another",
                "day_right")
    assert_one_error_line(r, "--database another day_right", "give one database traversal")


@pytest.mark.parametrize("args, fragments", [
    (["--tolerance", "2"], ("--tolerance counts frames of aligned traversals", "drop --tolerance")),
    (["--database", "database"], ("--database picks traversal folders", "drop --database")),
    (["--queries", "queries"], ("--queries picks traversal folders", "drop --queries")),
])
def test_database_queries_layout_refuses_traversal_options(database_queries_layout, capsys, args, fragments):
    r = refused(capsys, "acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels", *args)
    assert_one_error_line(r, *fragments)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("args, fragments", [
    (["--tau", "baseline=0.5"], ("--tau baseline=0.5", "thresholds of its own", "seqslam")),
    (["--tau", "seqslam"], ("--tau seqslam", "RULE=VALUE")),
    (["--tau", "nope=1"], ("--tau nope=1", "'nope' is not a rule")),
    (["--tau", "seqslam=nan"], ("--tau seqslam=nan", "finite")),
    (["--tau", "seqslam=x"], ("--tau seqslam=x", "finite")),
    (["--tau", "seqslam=1", "--tau", "seqslam=2"], ("--tau seqslam given twice",)),
    (["--tau", "seqslam=1", "--rules", "baseline"], ("--tau seqslam=1", "not among --rules baseline")),
    (["--rules", "baseline", "nope"], ("--rules nope", "choose from baseline")),
    (["--reference-share", "1.5"], ("--reference-share 1.5", "between 0 and 1")),
    (["--reference-share", "nan"], ("--reference-share nan",)),
    (["--fanout", "0"], ("--fanout 0", "1 or more")),
    (["--patch", "1"], ("--patch 1", "2 or more")),
    (["--ds", "1"], ("--ds 1", "2 or more")),
    (["--authors", "--places", "group-step"], ("--authors sets --places discovered", "--places group-step")),
    (["--authors", "--place-score", "best"], ("--authors sets --place-score mean",)),
    (["--authors", "--tolerance", "1"], ("--authors sets --tolerance 2",)),
    (["--authors", "--fanout", "3"], ("--authors sets --fanout 5",)),
    (["--database", "day", "night"], ("--database day night", "give one database traversal")),
    (["--queries", "dusk"], ("dusk",)),
    (["--database", "snow", "--queries", "snow"], ("snow",)),
    (["--tolerance", "-1"], ("--tolerance=-1", "0 or more")),
    (["--radius", "5"], ("--radius",)),
    (["--geometry", "route"], ("--geometry",)),
    (["--group", "3", "--step", "2"], ("step=2 < group=3",)),
])
def test_bad_input_is_one_error_line_naming_the_option(capsys, args, fragments):
    r = refused(capsys, "acceptance", "--dataset", "demo", "--descriptor", "pixels", *args)
    assert_one_error_line(r, *fragments)
    assert r.stdout == ""


def test_bad_input_exits_2_from_the_real_command(tmp_path):
    out = tmp_path / "never.json"
    r = run("acceptance", "--dataset", "demo", "--descriptor", "pixels", "--tau", "per-place=0.5",
            "--json", str(out))
    assert_one_error_line(r, "--tau per-place=0.5")
    assert not out.exists()


def test_unwritable_json_is_refused(capsys, tmp_path):
    r = refused(capsys, "acceptance", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
                "--rules", "baseline", "--json", str(tmp_path / "missing" / "x.json"))
    assert_one_error_line(r, "--json", "cannot write", alone=False)


def test_argparse_refuses_unknown_choices(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["acceptance", "--dataset", "demo", "--places", "everywhere"])
    assert exc.value.code == 2
    assert "argument --places: invalid choice: 'everywhere'" in capsys.readouterr().err


# --------------------------------------------------------------------------- the help


def test_help_restates_the_benchs_defaults_and_choices():
    defaults = BenchOptions()
    assert cli.BENCH_DEFAULTS == {"places": defaults.places.value, "place_score": defaults.place_score.value,
                                  "reference_share": defaults.reference_share, "patch": defaults.patch,
                                  "fanout": defaults.fanout, "ds": defaults.ds}
    assert cli.PLACES == tuple(x.value for x in PlaceSource) and cli.PLACE_SCORES == tuple(x.value for x in PlaceScore)
    assert cli.FREE_RULES == tuple(r.key for r in RULES if r.free)
    assert cli.AUTHORS == {"places": "discovered", "place_score": "mean", "tolerance": 2, "fanout": 5}
    r = run("acceptance", "--help")
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    for fragment in ("--reference-share REFERENCE_SHARE", "(default: 0.7)", "--tau RULE=VALUE",
                     "seqslam, top1-distance, pa-ratio, sue", "--authors", "(default: 2)", "(default: group-step)"):
        assert fragment in text, fragment


def test_the_parser_does_not_import_the_bench():
    # protocols.acceptance imports scipy.stats (about half a second): every command would start that much later
    code = ("import sys; from vpr_explorer.cli.parser import build_parser; build_parser(); "
            "print('vpr_explorer.protocols.acceptance' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"



# --------------------------------------------------------------------------- --vary


def gp_sweep(gardens_point, parameter: str, values, places=None):
    """``sweep_bench`` on GardensPoint day_left against day_right, called as the API documents it."""
    from vpr_explorer.protocols.acceptance_sweep import sweep_bench

    value = database_queries(gardens_point, "day_left", database=["day_right"], tolerance=2)
    labels, _ = retrieval_places(value, PlaceSpec(3, 10))
    return sweep_bench(value, dataset_descriptors(value, "pixels"), labels=labels, parameter=parameter, values=values,
                       places=places)


def test_vary_prints_the_sweep_and_writes_it(gardens_point, tmp_path, capsys):
    from vpr_explorer.protocols.acceptance_sweep import render

    out = tmp_path / "vary.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
                 "--vary", "ds=4,6", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    sweep = gp_sweep(gardens_point, "ds", [4, 6])
    assert render(sweep) in stdout
    assert stdout.index("rule ") < stdout.index("ds varied")  # the bench's table first, then the sweep's
    data = strict(out.read_text())
    assert_same_numbers(data, direct_report(gardens_point, BenchOptions()))  # the table at --ds, as without --vary
    want = plain(sweep.to_dict())
    assert data["sweep"]["points"] == want["points"]
    assert (data["sweep"]["parameter"], data["sweep"]["values"], data["sweep"]["recomputed"]) == (
        "ds", [4, 6], ["seqslam", "sequence-per-place"])
    assert data["sweep"]["settings"]["ds"] == [4, 6] and data["sweep"]["settings"]["descriptor"] == "pixels"


def test_vary_group_relabels_the_places(gardens_point, tmp_path, capsys):
    out = tmp_path / "group.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
                 "--vary", "group=1,5", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "group=1" in stdout and "group=5" in stdout
    data = strict(out.read_text())
    want = plain(gp_sweep(gardens_point, "group", [1, 5], PlaceSpec(3, 10)).to_dict())
    assert data["sweep"]["points"] == want["points"]


def test_vary_refuses_ds_where_the_sequence_rules_are_left_out(database_queries_layout, capsys):
    r = refused(capsys, "acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels",
                "--vary", "ds=4,6")
    line = assert_one_error_line(r, "--vary ds=4,6: ds (", "seqslam, sequence-per-place", "no database route in order")
    assert "leaves out here" in line
    r = refused(capsys, "acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels",
                "--vary", "reference_share=0.5")
    assert_one_error_line(r, "--vary reference_share=0.5", "natural open set", "not one route in order")


@pytest.mark.parametrize("args, fragments", [
    (["--vary", "ds"], ("--vary ds", "PARAM=V1,V2,...")),
    (["--vary", "ds="], ("--vary ds=", "PARAM=V1,V2,...")),
    (["--vary", "=4"], ("--vary =4", "PARAM=V1,V2,...")),
    (["--vary", "tolerance=1,2"], ("'tolerance' is not a parameter", "ds, patch, fanout, sue_k, reference_share")),
    (["--vary", "ds=4,six"], ("--vary ds=4,six", "'six' is not a whole number")),
    (["--vary", "reference-share=0.5,half"], ("'half' is not a number",)),
    (["--vary", "ds=4,1"], ("--vary ds=4,1: ds=1: a whole number, 2 or more",)),
    (["--vary", "patch=1"], ("--vary patch=1: patch=1: a whole number, 2 or more",)),
    (["--vary", "fanout=0"], ("--vary fanout=0: fanout=0",)),
    (["--vary", "reference_share=0.5,1"], ("--vary reference_share=0.5,1: reference_share=1",)),
    (["--vary", "group=5", "--step", "4"], ("--vary group=5: step=4 < group=5",)),
    (["--vary", "step=2.5"], ("--vary step=2.5: step=2.5", "whole number of frames")),
    (["--vary", "group=2", "--places", "discovered"], ("--vary group=2", "places='discovered'")),
    (["--vary", "ds=4", "--rules", "baseline"], ("--vary ds=4", "rules=['baseline'] leaves them out")),
    (["--vary", "sue-k=3"], ("--vary sue-k=3: sue_k", "not metres")),
    (["--soft-tolerance", "3"], ("--soft-tolerance 3", "add --tutorial-pr")),
    (["--tutorial-pr", "--soft-tolerance", "1"], ("--soft-tolerance 1 is below --tolerance 2",)),
    (["--tutorial-pr", "--tolerance", "9"], ("--soft-tolerance 8 (the default) is below --tolerance 9",)),
    (["--tutorial-pr", "--soft-tolerance", "-1"], ("--soft-tolerance=-1", "0 or more")),
])
def test_bad_vary_and_tutorial_options_are_one_error_line(capsys, args, fragments):
    r = refused(capsys, "acceptance", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
                *args)
    assert_one_error_line(r, *fragments)
    assert r.stdout == ""


def test_vary_names_restate_the_sweeps_parameters():
    from vpr_explorer.protocols.acceptance_sweep import Parameter

    assert tuple(cli.VARY) == tuple(p.value for p in Parameter)
    assert cli.SOFT_TOLERANCE == 8  # VPR_Tutorial's GardensPoint: np.ones((17, 1)) about the diagonal


# --------------------------------------------------------------------------- --tutorial-pr


def frame_truth(n: int, tolerance: int):
    """``(n, n)`` bool: |query frame − database frame| ≤ tolerance (GardensPoint: frame = image index)."""
    import numpy as np

    i = np.arange(n)
    return np.abs(i[:, None] - i[None, :]) <= tolerance


def test_tutorial_pr_is_tutorial_pr_on_the_closed_set(gardens_point, tmp_path, capsys):
    from vpr_explorer.method.retrieval import similarity
    from vpr_explorer.protocols.tutorial_pr import tutorial_pr

    out = tmp_path / "tutorial.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", "--queries",
                 "night_right", "--database", "day_right", "--rules", "baseline", "--tolerance", "0",
                 "--soft-tolerance", "5", "--tutorial-pr", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    data = strict(out.read_text())
    tutorial = data["tutorial_pr"]
    assert (tutorial["n_queries"], tutorial["n_database"]) == (200, 200)
    assert tutorial["hard"] == "same frame" and tutorial["soft"] == "within ±5 frames"
    assert data["settings"]["soft_tolerance"] == 5
    value = database_queries(gardens_point, "night_right", database=["day_right"], tolerance=0)
    d = dataset_descriptors(value, "pixels")
    s = similarity(d[200:], d[:200])
    hard, soft = frame_truth(200, 0), frame_truth(200, 5)
    rows = [line.split() for line in stdout.splitlines() if line.startswith(("single ", "multi "))]
    assert len(rows) == len(tutorial["curves"]) == 4
    for (matching, ignored), got, row in zip(cli.TUTORIAL_ROWS, tutorial["curves"], rows):
        want = tutorial_pr(s, hard, soft if ignored else None, matching=matching)
        assert got == plain({"ground_truth": "soft ignored" if ignored else "hard only", **want.to_dict()})
        assert row[0] == matching and " ".join(row[1:3]) == got["ground_truth"]
        assert row[3:] == [f"{want.auc:.3f}", f"{want.recall_at_100_precision:.3f}"]
    assert "VPR_Tutorial refuses soft positives with single matching" in stdout
    assert "R@100P: the largest recall at precision exactly 1" in stdout


def test_tutorial_pr_default_soft_tolerance_is_eight(gardens_point, tmp_path, capsys):
    out = tmp_path / "eight.json"
    assert main(["acceptance", "--dataset", str(gardens_point.root), "--descriptor", "pixels", *GP_PAIR,
                 "--rules", "baseline", "--tutorial-pr", "--json", str(out)]) == 0
    capsys.readouterr()
    tutorial = strict(out.read_text())["tutorial_pr"]
    assert tutorial["hard"] == "within ±2 frames" and tutorial["soft"] == "within ±8 frames"


def test_tutorial_pr_without_soft_positives(database_queries_layout, tmp_path, capsys):
    from vpr_explorer.method.retrieval import similarity
    from vpr_explorer.pipeline import open_dataset
    from vpr_explorer.protocols.tutorial_pr import tutorial_pr

    out = tmp_path / "dq_tutorial.json"
    assert main(["acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels", "--rules",
                 "baseline", "--tutorial-pr", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "no soft positives: the curves count hard positives only" in stdout
    tutorial = strict(out.read_text())["tutorial_pr"]
    assert tutorial["soft"] is None and [c["matching"] for c in tutorial["curves"]] == ["single", "multi"]
    value = open_dataset(str(database_queries_layout), "database-queries")
    d = dataset_descriptors(value, "pixels")
    hard = value.ground_truth.dense()
    kept = hard.any(axis=1)  # the closed set counts the queries with a right image
    s = similarity(d[value.n_database:], d[:value.n_database])[kept]
    for got in tutorial["curves"]:
        want = tutorial_pr(s, hard[kept], matching=got["matching"])
        assert got["auc"] == want.auc and got["recall_at_100_precision"] == want.recall_at_100_precision
    r = refused(capsys, "acceptance", "--dataset", str(database_queries_layout), "--descriptor", "pixels",
                "--tutorial-pr", "--soft-tolerance", "8")
    assert_one_error_line(r, "--soft-tolerance counts frames of aligned traversals", "drop --soft-tolerance")
