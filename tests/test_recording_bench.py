"""Playback with the acceptance bench: read the written .rrd back and check each rule's logged decisions.

The expectations come from ``protocols.acceptance.acceptance_report`` run here on the same
value and places, and each query's right or wrong from the ground truth by a plain loop over
the authors' counts (a genuine query, one with a right database image, is right when
accepted with a right image, a wrong accept when accepted with another, a wrong reject when
rejected; a distractor is right when rejected; the closed set does not count distractors),
not from the recording module's helpers. The .rrd is read back as ``tests/test_recording.py``
reads it (``read_rrd``: rerun's own ``RrdReader``).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from test_app import assert_clean, fresh_caches, navigation_mode, page  # noqa: F401  (autouse fixtures)
from test_recording import aligned_value, read_rrd

from vpr_explorer.cli import main
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceSpec, retrieval_places
from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset
from vpr_explorer.protocols import acceptance
from vpr_explorer.protocols.acceptance import BenchOptions, acceptance_report
from vpr_explorer.recording import TITLE_CHARS, bench_report, playback_blueprint, record_playback

SERIES = ("confidence", "accepted", "decision")
LEVEL = {"right": "INFO", "wrong accept": "ERROR", "wrong reject": "WARN", "not counted": "DEBUG"}


def expected_verdicts(answer, accepted, hard, genuine, counted) -> list[str]:
    """The authors' counts, one query at a time."""
    out = []
    for q in range(len(answer)):
        if not counted[q]:
            out.append("not counted")
        elif genuine[q]:
            if accepted[q]:
                out.append("right" if hard[q, answer[q]] else "wrong accept")
            else:
                out.append("wrong reject")
        else:
            out.append("wrong accept" if accepted[q] else "right")
    return out


def check_rule(temporal, root: str, bench, key: str, value, hard) -> list[str]:
    """The rule's logged accepted flags, confidences and decisions equal the bench's, frame by frame.

    Returns:
        The level of each query's logged decision.
    """
    d = bench.decisions[key]
    n = value.n_queries
    accepted = temporal[f"/{root}/{key}/accepted"]
    assert sorted(accepted) == list(range(n))
    np.testing.assert_array_equal([accepted[q]["Scalars:scalars"][0] for q in range(n)],
                                  d.accepted.astype(np.float64))
    confidence = temporal[f"/{root}/{key}/confidence"]
    finite = np.flatnonzero(np.isfinite(d.confidence))
    assert sorted(confidence) == finite.tolist()  # no entry where the rule has no candidate (−inf)
    np.testing.assert_array_equal([confidence[q]["Scalars:scalars"][0] for q in finite], d.confidence[finite])
    said = expected_verdicts(d.answer, d.accepted, hard, bench.genuine, bench.counted)
    levels = []
    for q in range(n):
        log = temporal[f"/{root}/{key}/decision"][q]
        (text,) = log["TextLog:text"]
        assert log["TextLog:level"] == [LEVEL[said[q]]], (root, key, q, text)
        levels.append(log["TextLog:level"][0])
        assert text.startswith(f"query {q} · {key}: "), text
        candidate = int(d.candidate[q])
        if d.accepted[q]:
            head = f"accepted database image {candidate}, "
        elif candidate >= 0:
            head = f"rejected its candidate, database image {candidate}, "
        else:
            head = "rejected, no candidate"
        assert head in text, text
        if candidate >= 0:
            path = value.database_paths[candidate]
            assert f"{path.parent.name}/{path.name}" in text, text
        verdict = re.search(r"\((right|wrong|not counted)\b", text)
        assert verdict is not None, text
        assert verdict.group(1) == ("not counted" if said[q] == "not counted" else said[q].split()[0]), text
    return levels


def bench_entities(temporal: dict, root: str) -> set[str]:
    return {e for e in temporal if e.startswith(f"/{root}/")}


# --------------------------------------------------------------------------- GardensPoint, night against day


@pytest.fixture(scope="module")
def gp_bench(gardens_point, gp_pixels, tmp_path_factory):
    """night_right against day_right (pixels, group 3 step 10) recorded with and without the bench."""
    value, d, fitted = aligned_value(gardens_point, gp_pixels, "night_right", ["day_right"])
    labels = retrieval_places(value, PlaceSpec(3, 10))[0]
    report = acceptance_report(value, d, labels=labels, settings={"descriptor": "pixels"})
    folder = tmp_path_factory.mktemp("bench")
    with_bench = record_playback(fitted, d, out=folder / "bench.rrd", descriptor="pixels", bench=report)
    without = record_playback(fitted, d, out=folder / "plain.rrd", descriptor="pixels")
    return value, d, fitted, report, with_bench, without


@pytest.mark.realdata
@pytest.mark.parametrize("root, which", [("bench", "closed"), ("bench_open", "natural")])
def test_gardens_point_bench_logs_each_rule_per_frame(gp_bench, root, which):
    value, _, _, report, playback, _ = gp_bench
    bench = getattr(report, which)
    assert bench is not None, report.natural_note
    temporal, static = read_rrd(playback.rrd)
    hard = value.ground_truth.dense()
    assert bench_entities(temporal, root) == {f"/{root}/{key}/{s}" for key in bench.decisions for s in SERIES}
    for key in ("per-place", "seqslam", "per-query-graph"):
        levels = check_rule(temporal, root, bench, key, value, hard)
        c = bench.counts[key]
        assert (levels.count("INFO"), levels.count("ERROR"), levels.count("WARN")) == (c.tp + c.tn, c.fp, c.fn)
        assert levels.count("DEBUG") == int((~bench.counted).sum())
    # SeqSLAM has no candidate for ds/2 queries at either end: those frames hold no confidence
    assert not np.isfinite(bench.decisions["seqslam"].confidence).all()
    if which == "natural":
        assert not bench.genuine.all() and bench.counted.all()  # distractors: rejecting them is right


@pytest.mark.realdata
def test_gardens_point_a_rule_left_out_logs_nothing_and_the_recording_says_why(gp_bench):
    _, _, _, report, playback, _ = gp_bench
    temporal, static = read_rrd(playback.rrd)
    assert "sue" in report.closed.left_out and "sue" in report.natural.left_out  # GardensPoint's positions
    (note,) = [n for n in report.notes if n.startswith("sue left out: ")]
    why = note[len("sue left out: "):]
    for root in ("bench", "bench_open"):
        assert not any(e.startswith(f"/{root}/sue") for e in (*temporal, *static))
        summary = static[f"/{root}/summary"]["TextDocument:text"][0]
        assert f"- **sue** ({acceptance.RULES_BY_KEY['sue'].label}): {why}" in summary
        assert "## Left out (nothing logged)" in summary
        for key, d in getattr(report, "closed" if root == "bench" else "natural").decisions.items():
            assert f"- **{key}** ({d.rule.label}): F1 " in summary
    assert "sue left out: " + why in playback.describe()


@pytest.mark.realdata
def test_gardens_point_bench_adds_entities_only(gp_bench):
    """Every entity of the playback is logged as without the bench."""
    *_, playback, without = gp_bench
    bench, plain = read_rrd(playback.rrd), read_rrd(without.rrd)
    for got, want in zip(bench, plain):
        assert {e: v for e, v in got.items() if not e.startswith(("/bench/", "/bench_open/"))} == want


@pytest.mark.realdata
def test_bench_report_runs_the_bench_on_the_recorded_value_and_places(gp_bench):
    value, d, fitted, report, playback, _ = gp_bench
    again = bench_report(fitted, d, descriptor="pixels")
    assert again.settings["descriptor"] == "pixels" and "group 3, step 10" in again.settings["group/step"]
    for which in ("closed", "natural"):
        a, b = getattr(report, which), getattr(again, which)
        assert list(a.decisions) == list(b.decisions) and a.left_out == b.left_out
        for key in a.decisions:
            np.testing.assert_array_equal(a.decisions[key].accepted, b.decisions[key].accepted)
            np.testing.assert_array_equal(a.decisions[key].confidence, b.decisions[key].confidence)
    assert playback.bench is report


# --------------------------------------------------------------------------- the demo route


@pytest.fixture(scope="module")
def demo():
    dataset = resolve_dataset("demo")
    return dataset, dataset_descriptors(dataset, "pixels")


def test_several_database_traversals_leave_the_sequence_rules_and_the_open_set_out(demo, tmp_path):
    dataset, desc = demo
    value, d, fitted = aligned_value(dataset, desc, "snow", ["day", "night"], PlaceSpec(2, 2))
    report = bench_report(fitted, d)
    sequence = {"per-query", "per-query-graph", "seqslam", "sequence-per-place"}
    assert sequence <= set(report.closed.left_out) and report.natural is None
    playback = record_playback(fitted, d, out=tmp_path / "two.rrd", bench=report)
    temporal, static = read_rrd(playback.rrd)
    assert bench_entities(temporal, "bench") == {f"/bench/{k}/{s}" for k in report.closed.decisions for s in SERIES}
    assert not bench_entities(temporal, "bench_open")
    summary = static["/bench/summary"]["TextDocument:text"][0]
    for key in sequence:
        assert f"- **{key}** ({acceptance.RULES_BY_KEY[key].label}): {report.closed.left_out[key]}" in summary
    assert static["/bench_open/summary"]["TextDocument:text"][0].endswith(f"Not run: {report.natural_note}\n")
    assert "bench, open set: not run" in playback.describe()
    check_rule(temporal, "bench", report.closed, "baseline", value, value.ground_truth.dense())


def test_chosen_rules_only(demo, tmp_path):
    dataset, desc = demo
    value, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    report = bench_report(fitted, d, options=BenchOptions(rules=("per-place", "pa-ratio")))
    temporal, _ = read_rrd(record_playback(fitted, d, out=tmp_path / "two.rrd", bench=report).rrd)
    for root, bench in (("bench", report.closed), ("bench_open", report.natural)):
        assert bench_entities(temporal, root) == {f"/{root}/{k}/{s}" for k in ("per-place", "pa-ratio") for s in SERIES}
        check_rule(temporal, root, bench, "pa-ratio", value, value.ground_truth.dense())


def test_a_report_of_another_value_is_refused(demo, tmp_path):
    dataset, desc = demo
    _, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    _, d2, other = aligned_value(dataset, desc, "snow", ["day", "night"], PlaceSpec(2, 2))
    with pytest.raises(VPRInputError, match="bench: the report is of 'demo' .*run the bench on the value recorded"):
        record_playback(fitted, d, out=tmp_path / "x.rrd", bench=bench_report(other, d2))
    # same sizes, other right images: a tolerance of 2 frames instead of 0
    _, d3, wider = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2), tolerance=2)
    with pytest.raises(VPRInputError, match="other right images"):
        record_playback(fitted, d, out=tmp_path / "x.rrd", bench=bench_report(wider, d3))
    assert not (tmp_path / "x.rrd").exists()


def test_blueprint_with_the_bench_shows_its_views():
    bp = playback_blueprint("night", ["day"], bench=True)
    views = {}

    def walk(node):
        if not hasattr(node, "origin"):
            for c in node.contents:
                walk(c)
            return
        views[str(node.name)] = str(node.origin)

    walk(bp.root_container)
    assert len(views) == 11 + 6 and all(len(n) <= TITLE_CHARS for n in views), views
    assert {"/bench/summary", "/bench", "/bench_open/summary", "/bench_open"} <= {
        "/" + o.strip("/") for o in views.values()}


def test_cli_record_with_the_bench(demo, tmp_path, capsys):
    dataset, desc = demo
    out = tmp_path / "run.rrd"
    rc = main(["record", "--dataset", "demo", "--database", "day", "--queries", "night", "--descriptor", "pixels",
               "--group", "2", "--step", "2", "--out", str(out), "--bench"])
    assert rc == 0
    printed = capsys.readouterr().out
    value, d, fitted = aligned_value(dataset, desc, "night", ["day"], PlaceSpec(2, 2))
    report = acceptance_report(value, d, labels=retrieval_places(value, PlaceSpec(2, 2))[0])
    assert f"bench, closed set: {len(report.closed.decisions)} rules logged under bench/" in printed
    temporal, _ = read_rrd(out)
    hard = value.ground_truth.dense()
    for root, bench in (("bench", report.closed), ("bench_open", report.natural)):
        assert bench_entities(temporal, root) == {f"/{root}/{k}/{s}" for k in bench.decisions for s in SERIES}
        for key in ("per-place-k", "per-query"):
            check_rule(temporal, root, bench, key, value, hard)


def test_cli_bench_refused_by_name_before_any_work(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(acceptance, "BENCH_PAIRS", 100)
    out = tmp_path / "run.rrd"
    rc = main(["record", "--dataset", "demo", "--database", "day", "--queries", "night", "--descriptor", "pixels",
               "--out", str(out), "--bench"])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("error: bench: 'demo' has 60 queries × 60 database images = 3,600 pairs"), err
    assert "record without the bench" in err and "descriptors" not in err
    assert not out.exists()


def test_playback_page_records_the_bench_when_asked(tmp_path):
    from streamlit.testing.v1 import AppTest

    from vpr_explorer.app import ENTRY

    at = page(AppTest.from_file(str(ENTRY), default_timeout=60).run(), "playback")
    assert_clean(at)
    box = at.checkbox(key="w_playback_bench")
    assert not box.value and len(box.help) >= 80
    at.button[0].click().run()
    assert_clean(at)
    assert at.session_state["playback"].bench is None
    at.checkbox(key="w_playback_bench").check().run()
    at.button[0].click().run()
    assert_clean(at)
    playback = at.session_state["playback"]
    report = playback.bench
    assert report is not None and report.settings["dataset"] == playback.dataset
    temporal, static = read_rrd(playback.rrd)
    assert bench_entities(temporal, "bench") == {f"/bench/{k}/{s}" for k in report.closed.decisions for s in SERIES}
    assert "/bench/summary" in static and "/bench_open/summary" in static
    assert any(c.value.startswith("Acceptance bench recorded with it: bench, closed set: ") for c in at.caption)
