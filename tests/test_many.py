"""``vpr-explorer bench`` (``protocols.many``, ``views.many_report``): many runs in one, against separate runs.

One real bench (GardensPoint Walking and the demo route, pixel descriptors, the paper,
traversal and open-set protocols, 3 runs, a dataset that does not exist) runs once for the
module; every cell's numbers are checked against a separate ``python -m vpr_explorer.cli
evaluate ... --pr --json`` of the same settings (equal, not close), the table's columns
against that run's JSON, the CSV and JSON read back, and the HTML report scanned for
anything it would load from elsewhere. Then the default protocol per layout on a
database/queries layout (GardensPoint written by ``data.example_layouts``), descriptors
computed once per dataset × descriptor, the memory measure, and bad options.
"""

from __future__ import annotations

import csv
import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from tests.cli_run import assert_one_error_line, refused, run
from vpr_explorer import pipeline
from vpr_explorer.cli import main
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.many import BenchSpec, measured, run_bench

pytestmark = pytest.mark.realdata

RUNS = 3
PROTOCOLS = ("paper", "traversal", "open-set")
MISSING = "no-such-dataset"


def strict(text: str):
    """``json.loads`` that refuses NaN and ±Infinity."""
    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def numbers(evaluation: dict) -> dict:
    """An evaluation's JSON without its time and curves: every number, setting and note."""
    return {k: v for k, v in evaluation.items() if k not in ("seconds", "pr_curves")}


@pytest.fixture(scope="module")
def bench(data_root, tmp_path_factory):
    """The module's bench: ``(exit status, stdout, out folder, bench.json)``."""
    out = tmp_path_factory.mktemp("bench") / "out"
    gp = str(data_root / "GardensPointWalking")
    code = main(["bench", "--datasets", gp, "demo", str(out.parent / MISSING), "--descriptors", "pixels",
                 "--protocols", *PROTOCOLS, "--runs", str(RUNS), "--unknown-share", "0.4", "--out", str(out)])
    return code, out, strict((out / "bench.json").read_text())


def evaluate_alone(dataset: str, protocol: str, tmp_path) -> dict:
    """``vpr-explorer evaluate`` of one cell, in its own process, written by hand from ``evaluate``'s options."""
    args = ["evaluate", "--dataset", dataset, "--descriptor", "pixels", "--protocol", protocol, "--pr",
            "--json", str(tmp_path / f"{protocol}.json")]
    if protocol in ("paper", "open-set"):
        args += ["--runs", str(RUNS)]
    if protocol == "open-set":
        args += ["--unknown-share", "0.4"]
    r = run(*args)
    assert r.returncode == 0, r.stderr[-2000:]
    return strict((tmp_path / f"{protocol}.json").read_text())


def test_every_cell_equals_a_separate_evaluate(bench, data_root, tmp_path):
    code, out, data = bench
    ran = [c for c in data["cells"] if c["error"] is None]
    assert [(c["dataset"], c["protocol"]) for c in ran] == [
        (name, p) for name in ("GardensPointWalking", "demo") for p in PROTOCOLS]
    rows = data["rows"]
    for cell in ran:
        alone = evaluate_alone(cell["source"], cell["protocol"], tmp_path)
        assert numbers(cell["evaluation"]) == numbers(alone), (cell["dataset"], cell["protocol"])
        assert alone["settings"]["descriptor"] == "pixels"
        # the table's columns are that run's numbers
        mine = [r for r in rows if r["source"] == cell["source"] and r["protocol"] == cell["protocol"]]
        assert [r["method"] for r in mine] == [m["key"] for m in alone["methods"]]
        pr = {p["key"]: p for p in alone["pr"]}
        for r, m in zip(mine, alone["methods"]):
            assert r["status"] == "ok" and r["label"] == m["label"]
            for k in (1, 5, 10):
                assert r[f"r{k}"] == m["recall"][str(k)]["mean"] and r[f"r{k}_std"] == m["recall"][str(k)]["std"]
            assert (r["auc"], r["r_at_100p"], r["max_f1"]) == (pr[r["method"]]["auc"], pr[r["method"]]["r_at_100p"],
                                                                pr[r["method"]]["max_f1"])
            rejection = m["unknown_rejection"]
            assert r["rejection"] == (None if rejection is None else rejection["mean"])
        if cell["protocol"] == "open-set":  # the rejection column is there where it applies
            assert all(r["rejection"] is not None for r in mine)
            assert cell["evaluation"]["settings"]["unknown_share"] == 0.4
        else:
            assert all(r["rejection"] is None for r in mine)
        # the command the JSON gives for the cell is that run's, option for option
        assert cell["evaluate"].split()[:4] == ["vpr-explorer", "evaluate", "--dataset", cell["source"]]
        assert ("--unknown-share 0.4" in cell["evaluate"]) == (cell["protocol"] == "open-set")
        assert (f"--runs {RUNS}" in cell["evaluate"]) == (cell["protocol"] != "traversal")


def test_a_bad_dataset_fails_alone(bench):
    code, out, data = bench
    assert code == 1 and data["failed"] == len(PROTOCOLS)
    failed = [c for c in data["cells"] if c["error"] is not None]
    assert [c["protocol"] for c in failed] == list(PROTOCOLS)
    assert all(c["source"].endswith(MISSING) and "does not exist" in c["error"] and c["evaluation"] is None
               for c in failed)
    bad = [r for r in data["rows"] if r["source"].endswith(MISSING)]
    assert [r["status"] for r in bad] == ["failed"] * len(PROTOCOLS) and all(r["r1"] is None for r in bad)
    assert next(d for d in data["datasets"] if d["source"].endswith(MISSING))["error"]
    # the others ran: one descriptors step each, reused by their three protocols
    steps = data["descriptors"]
    assert [(s["dataset"].split("/")[-1], s["descriptor"]) for s in steps] == [
        ("GardensPointWalking", "pixels"), ("demo", "pixels")]
    assert [s["n_images"] for s in steps] == [600, 180] and all(s["dim"] == 2048 for s in steps)
    assert all(s["seconds"] > 0 and s["python_peak_bytes"] > 0 and s["rss_growth_bytes"] >= 0 for s in steps)


def test_csv_and_json_read_back(bench):
    code, out, data = bench
    with open(out / "bench.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert len(table) == len(data["rows"]) == 2 * len(PROTOCOLS) * 8 + len(PROTOCOLS)
    for line, row in zip(table, data["rows"]):
        for key in ("dataset", "descriptor", "protocol", "method", "status"):
            assert line[key] == row[key]
        for key in ("r1", "r1_std", "r5", "r10", "auc", "r_at_100p", "max_f1", "rejection", "extract_seconds",
                    "python_peak_mib"):
            assert (float(line[key]) if line[key] else None) == row[key], key
        assert line["setting_runs"] == str(RUNS) and line["setting_unknown_share"] == "0.4"
    settings = data["settings"]
    assert settings["protocols"] == list(PROTOCOLS) and settings["runs"] == RUNS and settings["pr"] is True
    assert settings["given"] == ["runs", "unknown_share"] and settings["seed"] == 0 and settings["group"] == 3
    assert set(data["columns"]) == set(data["rows"][0])


class _Links(HTMLParser):
    """Every ``src``/``href`` of the document's elements, and each ``<script>``'s ``src``."""

    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("src", "href", "data", "action", "poster") and value:
                self.links.append(value)
            if name == "id":
                self.ids.add(value)


EXTERNAL = re.compile(r"""(?:src|href)\s*=\s*["']?\s*(?:https?:)?//""", re.IGNORECASE)


def test_the_report_loads_nothing_and_draws_each_dataset(bench):
    from plotly.offline import get_plotlyjs

    code, out, data = bench
    page = (out / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>")
    parser = _Links()
    parser.feed(page)
    assert not [link for link in parser.links if re.match(r"(?:[a-z]+:)?//", link, re.IGNORECASE)], parser.links
    assert "<link" not in page and "@import" not in page and "<script src" not in page.replace(" ", "")
    # Plotly's library is inlined once; apart from it (whose code holds link texts it never loads here: its logo's
    # link is hidden, map tiles are not drawn), nothing in the page names a resource elsewhere
    library = get_plotlyjs()
    assert page.count(library) == 1
    rest = page.replace(library, "")
    assert not EXTERNAL.findall(rest) and "url(http" not in rest
    # each dataset that ran has its figure in its section; the missing one says why it has none
    for k, d in enumerate(data["datasets"], 1):
        section = page.split(f'<section class="dataset" id="dataset-{k}"')[1].split("</section>")[0]
        if d["error"] is None:
            assert f'id="dataset-{k}-summary"' in section and f'"dataset-{k}-summary"' in section
            assert f"{d['name']}: every method, descriptor and protocol" in section
            assert section.count("Plotly.newPlot") == 1 + len(PROTOCOLS) + 1  # summary, a PR per cell, trade-off
        else:
            assert "cannot be read" in section and "Plotly.newPlot" not in section
    for cell in data["cells"]:
        if cell["error"] is None:
            assert cell["evaluate"].replace('"', "&quot;") in page
        else:
            assert cell["error"].split(":")[-1].strip() in page


def test_a_folder_that_holds_files_is_refused(capsys, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    args = ["bench", "--datasets", "demo", "--descriptors", "pixels", "--runs", "2", "--out", str(out)]
    assert_one_error_line(refused(capsys, *args), "--out", "--overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert main([*args, "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["bench.csv", "bench.json", "keep.txt", "report.html"]
    assert (out / "keep.txt").read_text() == "mine"
    stdout = capsys.readouterr().out
    assert stdout.startswith("1 cells (0 failed)") and "demo  " in stdout and "margin, weighted θ" in stdout
    file = tmp_path / "file"
    file.write_text("")
    assert_one_error_line(refused(capsys, *args[:-1], str(file)), "a file, not a folder")


@pytest.mark.parametrize("extra, fragments", [
    (["--descriptors", "no-such-net"], ["no-such-net", "unknown"]),
    (["--descriptors", "pixels", "pixels"], ["given twice"]),
    (["--descriptors", "pixels", "--methods", "margin"], ["methods", "margin"]),
    (["--descriptors", "pixels", "--methods", "global-user"], ["global-user", "theta"]),
    (["--descriptors", "pixels", "--protocols", "paper", "--k", "1"], ["--k-grid", "open-set"]),
    (["--descriptors", "pixels", "--protocols", "paper", "--database", "day"], ["--database", "traversal"]),
    (["--descriptors", "pixels", "--runs", "0"], ["runs=0"]),
    (["--descriptors", "pixels", "--unknown-share", "1.5"], ["unknown_share"]),
    (["--descriptors", "pixels", "--group", "0"], ["group=0"]),
    (["--descriptors-file", "other=x.npy"], ["--descriptors-file", "DATASET=FILE"]),
    ([], ["descriptors", "at least one"]),
])
def test_bad_options_exit_2_before_any_work(capsys, tmp_path, extra, fragments):
    out = tmp_path / "out"
    r = refused(capsys, "bench", "--datasets", "demo", "--out", str(out), *extra)
    assert_one_error_line(r, *fragments)
    assert not out.exists()


def test_an_option_no_default_protocol_reads_is_refused(capsys, tmp_path):
    # no --protocols: demo runs the paper protocol, which reads no k
    r = refused(capsys, "bench", "--datasets", "demo", "--descriptors", "pixels", "--k", "1", "--out",
                str(tmp_path / "out"))
    assert_one_error_line(r, "--k-grid", "open-set")


class Counting:
    """``vpr_explorer.pipeline`` with its dataset and descriptor calls counted."""

    def __init__(self):
        self.opened: list[str] = []
        self.extracted: list[tuple[str, str]] = []

    def __getattr__(self, name):
        return getattr(pipeline, name)

    def open_dataset(self, source, *args, **kwargs):
        self.opened.append(str(source))
        return pipeline.open_dataset(source, *args, **kwargs)

    def dataset_descriptors(self, dataset, descriptor, **kwargs):
        self.extracted.append((dataset.name, descriptor))
        return pipeline.dataset_descriptors(dataset, descriptor, **kwargs)


def test_descriptors_once_per_dataset_and_descriptor(tmp_path):
    stages = Counting()
    spec = BenchSpec(datasets=("demo",), descriptors=("pixels",), protocols=("paper", "open-set", "traversal"),
                     methods=("margin-weighted", "place-baseline"), runs=2, cache_root=tmp_path / "cache")
    labels = []
    result = run_bench(spec, stages, progress_for=lambda label: labels.append(label))
    assert stages.opened == ["demo"] and stages.extracted == [("demo", "pixels")]
    assert labels == ["demo · pixels", "demo · pixels · paper", "demo · pixels · open-set", "demo · pixels · traversal"]
    assert [r["method"] for r in result.rows()] == ["margin-weighted", "place-baseline"] * 3
    first = result.descriptors[0]
    assert first.cached_images == 0 and first.n_images == 180  # a new cache: every image extracted
    again = run_bench(spec, stages)
    assert again.descriptors[0].cached_images == 180
    for a, b in zip(result.cells, again.cells):  # the cache gives the same numbers
        assert a.evaluation.same_numbers(b.evaluation)


def test_the_default_protocol_of_each_layout(gardens_point, data_root, tmp_path):
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    layouts = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path / "layouts")
    folder = str(layouts["database-queries"])
    out = tmp_path / "out"
    assert main(["bench", "--datasets", "demo", folder, "--descriptors", "pixels", "--runs", "2", "--out",
                 str(out)]) == 0
    data = strict((out / "bench.json").read_text())
    assert [(c["dataset"], c["protocol"]) for c in data["cells"]] == [
        ("demo", "paper"), (data["datasets"][1]["name"], "database-queries")]
    assert data["datasets"][1]["layout"] == "database-queries"
    r = run("evaluate", "--dataset", folder, "--descriptor", "pixels", "--pr", "--json", str(tmp_path / "e.json"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert numbers(data["cells"][1]["evaluation"]) == numbers(strict((tmp_path / "e.json").read_text()))
    # a protocol the layout does not run fails its cell with evaluate's reason; the demo's still runs
    out2 = tmp_path / "out2"
    assert main(["bench", "--datasets", "demo", folder, "--descriptors", "pixels", "--protocols", "paper",
                 "--runs", "2", "--out", str(out2)]) == 1
    cells = strict((out2 / "bench.json").read_text())["cells"]
    assert cells[0]["error"] is None and "whose queries are given" in cells[1]["error"]


def test_measured_counts_the_blocks_allocations():
    with measured() as cost:
        block = np.ones(4 << 20)  # 32 MiB of float64
        del block
    assert cost["python_peak"] >= 32 << 20 and cost["seconds"] > 0 and cost["rss_growth"] >= 0
    with measured() as cost:
        pass
    assert cost["python_peak"] < 1 << 20


def test_spec_refuses_what_no_dataset_can_take():
    with pytest.raises(VPRInputError, match="datasets"):
        BenchSpec(datasets=())
    with pytest.raises(VPRInputError, match="not one of the datasets"):
        BenchSpec(datasets=("demo",), descriptor_files=(("other", "x.npy"),))
    with pytest.raises(VPRInputError, match="given twice"):
        BenchSpec(datasets=("demo",), descriptors=("pixels",), descriptor_files=(("demo", "a/pixels.npy"),))


def test_a_descriptor_file_is_one_more_descriptor(data_root, gardens_point, gp_pixels, tmp_path):
    from vpr_explorer.descriptors import write_descriptor_file

    gp = str(data_root / "GardensPointWalking")
    file = tmp_path / "gp_pixels.npz"
    write_descriptor_file(file, gp_pixels, gardens_point.image_paths, gardens_point.root)
    out = tmp_path / "out"
    assert main(["bench", "--datasets", gp, "--descriptors", "pixels", "--descriptors-file", f"{gp}={file}",
                 "--runs", "2", "--out", str(out)]) == 0
    data = strict((out / "bench.json").read_text())
    extracted, imported = data["cells"]
    assert (extracted["descriptor"], imported["descriptor"]) == ("pixels", "gp_pixels")
    assert imported["evaluation"]["settings"]["descriptors_file"] == str(file)
    for key in ("methods", "pr", "notes"):  # the same vectors: the same numbers
        assert imported["evaluation"][key] == extracted["evaluation"][key]
    step = data["descriptors"][1]
    assert step["descriptor"] == "gp_pixels" and step["cached_images"] is None and step["descriptors_file"] == str(file)
    assert f"--descriptors {file}" in imported["evaluate"]
    r = run("evaluate", "--dataset", gp, "--descriptors", str(file), "--runs", "2", "--pr", "--json",
            str(tmp_path / "e.json"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert numbers(imported["evaluation"]) == numbers(strict((tmp_path / "e.json").read_text()))


def test_a_dataset_option_the_layout_does_not_read_fails_its_cells(capsys, tmp_path):
    # evaluate refuses --radius and --geometry for traversal folders: the bench fails the demo's cells, and says why
    for extra, fragment in ((["--radius", "10"], "--radius applies to position-tagged layouts"),
                            (["--geometry", "route"], "--geometry applies to database/queries layouts"),
                            (["--protocols", "database-queries"], "needs a database/queries layout"),
                            (["--protocols", "paper", "--tolerance", "1000"], "tolerance=1000")):
        out = tmp_path / "-".join(extra)
        assert main(["bench", "--datasets", "demo", "--descriptors", "pixels", "--out", str(out), *extra]) == 1
        data = strict((out / "bench.json").read_text())
        assert len(data["cells"]) == 1 and fragment in data["cells"][0]["error"], data["cells"][0]["error"]
        assert data["descriptors"] == []  # nothing could use them: not computed
        assert "failed: demo · pixels · " in capsys.readouterr().out
