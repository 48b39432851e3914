"""The acceptance bench (``protocols.acceptance``) against plain loops of the authors' definitions and hand cases.

The references below are written from NickTrinh/VPR_Tutorial ``experiments/final_all_datasets.py``:
``evaluate`` (their counts over dicts of predictions), ``compute_adaptive_thresholds`` (explicit
lists of same-place and other-place scores), ``query_our_method`` (a loop over queries and
places with the mean place score), the baseline's ``argmax`` and the natural open set's
classification of queries by their ground-truth frame.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.graph_matcher import full_pipeline
from vpr_explorer.method.place_discovery import discovered_places
from vpr_explorer.method.places import PlaceSpec, retrieval_places
from vpr_explorer.method.retrieval import place_mean_scores, place_scores
from vpr_explorer.protocols.acceptance import (
    RULES,
    BenchOptions,
    acceptance_report,
    authors_counts,
    closed_set,
    metres_positions,
    natural_open_set,
    render_report,
    run_bench,
)

# --------------------------------------------------------------------------- the authors' definitions, as loops


def evaluate(predictions: dict, genuine: list, distractors: list, gt_map: dict, tolerance: int) -> dict:
    tp = fp = fn = tn = 0
    for q in genuine:
        gt = gt_map[q]
        if q in predictions:
            if any(abs(predictions[q] - r) <= tolerance for r in gt):
                tp += 1
            else:
                fp += 1
        else:
            fn += 1
    for q in distractors:
        if q in predictions:
            fp += 1
        else:
            tn += 1
    p = tp / max(tp + fp, 1) * 100
    r = tp / max(tp + fn, 1) * 100
    return {"TP": tp, "FP": fp, "FN": fn, "TN": tn, "P": p, "R": r, "F1": 2 * p * r / max(p + r, 1e-8),
            "rejection": tn / len(distractors) * 100 if distractors else None}


def adaptive_thresholds(ref: np.ndarray, places: list[list[int]]) -> list[float]:
    s = ref.astype(np.float64) @ ref.astype(np.float64).T
    out = []
    for pidx, place in enumerate(places):
        pos, neg = [], []
        for i in place:
            pos += [s[i, j] for j in place if j != i]
            for op, other in enumerate(places):
                if op != pidx:
                    neg += [s[i, j] for j in other]
        pos = np.array(pos) if pos else np.array([0.5])
        neg = np.array(neg)
        k = max(1.0, min((pos.mean() - neg.mean()) / max(neg.std(), 1e-8) / 2.0, 2.0))
        out.append(neg.mean() + k * neg.std())
    return out


def our_method(s: np.ndarray, places: list[list[int]], thresholds: list[float]) -> dict:
    accepted = {}
    for q in range(s.shape[0]):
        scores = [np.mean([float(s[q, j]) for j in place]) for place in places]
        surviving = [(pi, sc) for pi, sc in enumerate(scores) if sc >= thresholds[pi]]
        if surviving:
            best = max(surviving, key=lambda x: x[1])[0]
            accepted[q] = max(places[best], key=lambda j: s[q, j])
    return accepted


def as_lists(place: np.ndarray, n_places: int) -> list[list[int]]:
    return [list(np.flatnonzero(place == p)) for p in range(n_places)]


@pytest.fixture(scope="module")
def gp_left_right(gardens_point, gp_pixels):
    """The authors' GardensPoint: day_left reference, day_right queries, ±2 frames, 1-to-1."""
    value = database_queries(gardens_point, "day_right", database=["day_left"], tolerance=2)
    rows = value_rows(value)
    d = gp_pixels if rows is None else gp_pixels[rows]
    return value, np.asarray(d, dtype=np.float32)


def _authors_table(ref, query, share=0.7, tolerance=2):
    n_ref = len(ref)
    gt_map = {q: [q] for q in range(len(query))}
    out = {}
    for setting in ("closed", "natural"):
        if setting == "closed":
            r, genuine, distractors, gts = ref, sorted(gt_map), [], gt_map
        else:
            cut = int(n_ref * share)
            r = ref[:cut]
            genuine = [q for q in range(len(query)) if gt_map[q][0] < cut]
            distractors = [q for q in range(len(query)) if gt_map[q][0] >= cut]
            gts = {q: gt_map[q] for q in genuine}
        s = query @ r.T
        baseline = {q: int(np.argmax(s[q])) for q in range(len(query))}
        place, n = discovered_places(r)
        places = as_lists(place, n)
        ours = our_method(s, places, adaptive_thresholds(r, places))
        match, _ = full_pipeline(s)
        vys = {q: int(m) for q, m in enumerate(match.matched) if m >= 0}
        out[setting] = {name: evaluate(pred, genuine, distractors, gts, tolerance)
                        for name, pred in (("baseline", baseline), ("per-place-k", ours), ("per-query-graph", vys))}
    return out


def test_the_authors_pipeline_as_their_loops_count_it(gp_left_right):
    value, d = gp_left_right
    options = BenchOptions(places="discovered", place_score="mean", rules=("baseline", "per-place-k",
                                                                           "per-query-graph"))
    report = acceptance_report(value, d, labels=None, options=options)
    _check_against_loops(report.closed, report.natural, _authors_table(d[:value.n_database], d[value.n_database:]))
    # the natural open set of GardensPoint: 140 frames kept, 60 queries past the cut are distractors
    assert report.natural.counts["baseline"].n_genuine == 140
    assert report.natural.counts["baseline"].n_distractor == 60
    assert report.closed.counts["baseline"].n_distractor == 0


def test_the_authors_pipeline_on_a_stretch_of_nordland(data_root):
    """Winter reference, summer queries (the authors' Nordland direction), frames 1000–1299, pixels."""
    from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset

    ds = resolve_dataset(data_root / "Nordland_64x32")
    d = dataset_descriptors(ds, "pixels")
    def rows(name):  # descriptors are in traversal order, frames within
        start = ds.traversals.index(name) * ds.n_frames
        return np.asarray(d[start + 1000:start + 1300], dtype=np.float32)

    ref, query = rows("winter"), rows("summer")
    n = len(ref)
    frame = np.arange(n)
    hard = np.abs(frame[:, None] - frame[None, :]) <= 2
    exact = np.eye(n, dtype=bool)
    options = BenchOptions(places="discovered", place_score="mean", rules=("baseline", "per-place-k",
                                                                           "per-query-graph"))
    s = query @ ref.T
    closed = closed_set(s, ref, hard, labels=None, sequence=None, options=options, exact=exact)
    natural = natural_open_set(s, ref, hard, labels=None, sequence=None, ordered=True, options=options, exact=exact)
    _check_against_loops(closed, natural, _authors_table(ref, query))
    assert natural.counts["per-place-k"].tn > 0  # the authors' rule rejects some distractors here


def _check_against_loops(closed, natural, expected):
    for setting, bench in (("closed", closed), ("natural", natural)):
        for key, want in expected[setting].items():
            got = bench.counts[key]
            assert (got.tp, got.fp, got.fn, got.tn) == (want["TP"], want["FP"], want["FN"], want["TN"]), (setting, key)
            assert got.f1 == pytest.approx(want["F1"], abs=1e-9)
            assert got.precision == pytest.approx(want["P"]) and got.recall == pytest.approx(want["R"])
            if want["rejection"] is None:
                assert got.rejection is None
            else:
                assert got.rejection == pytest.approx(want["rejection"])


def test_the_authors_answers_query_by_query(gp_left_right):
    """Not only the counts: every accepted answer of the authors' per-place rule is the loop's."""
    value, d = gp_left_right
    ref, query = d[:value.n_database], d[value.n_database:]
    s = query @ ref.T
    place, n = discovered_places(ref)
    places = as_lists(place, n)
    want = our_method(s, places, adaptive_thresholds(ref, places))
    bench = run_bench(s, ref, value.ground_truth.dense(), labels=None, sequence=None,
                      options=BenchOptions(places="discovered", place_score="mean", rules=("per-place-k",)))
    dec = bench.decisions["per-place-k"]
    got = {q: int(a) for q, a in enumerate(dec.answer) if dec.accepted[q]}
    assert got == want
    assert 0 < len(got) < value.n_queries  # the rule both accepts and rejects here


def test_counts_by_hand():
    hard = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 0]], dtype=bool)
    genuine = hard.any(axis=1)
    # q0 accepted right, q1 accepted wrong, q2 (distractor) accepted, q3 (distractor) rejected
    c = authors_counts(np.array([0, 2, 1, -1]), np.array([True, True, True, False]), hard, genuine)
    assert (c.tp, c.fp, c.fn, c.tn) == (1, 2, 0, 1)
    assert c.precision == pytest.approx(100 / 3) and c.recall == pytest.approx(100.0)
    assert c.recall_all == pytest.approx(50.0)  # the accepted wrong genuine query is a miss here
    assert c.rejection == pytest.approx(50.0)
    assert c.f1 == pytest.approx(2 * (100 / 3) * 100 / (100 / 3 + 100))
    # q1 rejected instead: a false negative
    c = authors_counts(np.array([0, -1, 1, -1]), np.array([True, False, True, False]), hard, genuine)
    assert (c.tp, c.fp, c.fn, c.tn) == (1, 1, 1, 1)
    # no distractors: rejection is None, not 0
    assert authors_counts(np.array([0]), np.array([True]), hard[:1], genuine[:1]).rejection is None


def test_place_mean_scores_against_a_loop():
    rng = np.random.default_rng(3)
    sims = rng.uniform(-1, 1, (5, 9))
    labels = np.array([2, 0, 0, 1, 2, 2, 0, 1, 1])
    got = place_mean_scores(sims, labels, 4)
    for q in range(5):
        for p in range(3):
            assert got[q, p] == pytest.approx(np.mean([sims[q, j] for j in range(9) if labels[j] == p]), abs=1e-15)
    assert np.all(got[:, 3] == -np.inf)  # a place without images
    with pytest.raises(VPRInputError, match="place labels"):
        place_mean_scores(sims, labels[:4], 4)
    # the mean differs from the best: a place of one high and one low image
    s = np.array([[0.9, 0.1, 0.6, 0.6]])
    assert place_mean_scores(s, np.array([0, 0, 1, 1]), 2)[0].tolist() == pytest.approx([0.5, 0.6])
    assert place_scores(s, np.array([0, 0, 1, 1]), 2)[0][0].tolist() == pytest.approx([0.9, 0.6])


def _unit(x):
    x = np.asarray(x, dtype=np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_a_place_score_at_its_threshold_is_kept_and_one_float_below_is_not():
    """raw_p ≥ θ_p: the least float32 score at or above θ_p keeps the place; the next float32 below drops it."""
    rng = np.random.default_rng(0)
    db = _unit(rng.normal(size=(12, 8)))
    labels = np.repeat(np.arange(4), 3)
    q = _unit(rng.normal(size=(3, 8)))
    s = q @ db.T
    hard = np.zeros_like(s, dtype=bool)
    hard[:, 0] = True
    options = BenchOptions(rules=("per-place",))
    dec = run_bench(s, db, hard, labels=labels, sequence="x", options=options).decisions["per-place"]
    theta = dec.detail["theta"]  # θ of the place each query answers (the same for every query: one database)
    p = int(dec.detail["place"][0])
    at = np.float32(theta[0])
    if at < theta[0]:
        at = np.nextafter(at, np.float32(np.inf))
    below = np.nextafter(at, np.float32(-np.inf))
    for value, accepted in ((at, True), (below, False)):
        s2 = np.full_like(s, -1.0)
        s2[:, labels == p] = value  # place p scores `value`, every other place −1
        got = run_bench(s2, db, hard, labels=labels, sequence="x", options=options).decisions["per-place"]
        assert got.accepted.tolist() == [accepted] * len(q)
        if accepted:
            assert got.detail["raw"].tolist() == [float(value)] * len(q)


def test_oracle_tau_is_the_best_f1_over_every_cut(gp_left_right):
    value, d = gp_left_right
    ref, query = d[:value.n_database], d[value.n_database:]
    s = query @ ref.T
    hard = value.ground_truth.dense()
    bench = run_bench(s, ref, hard, labels=None, sequence=None, options=BenchOptions(rules=("pa-ratio",)))
    dec = bench.decisions["pa-ratio"]
    best = -1.0
    for tau in np.unique(-dec.confidence):
        acc = dec.candidate >= 0
        acc &= dec.confidence >= -tau
        best = max(best, authors_counts(np.where(acc, dec.candidate, -1), acc, hard, hard.any(axis=1)).f1)
    assert bench.counts["pa-ratio"].f1 == pytest.approx(best)
    assert dec.tau_note.startswith("oracle")
    # a given τ is used as given
    fixed = run_bench(s, ref, hard, labels=None, sequence=None,
                      options=BenchOptions(rules=("pa-ratio",), taus={"pa-ratio": 0.5}))
    d2 = fixed.decisions["pa-ratio"]
    assert d2.tau == 0.5 and d2.tau_note == "given"
    assert d2.accepted.tolist() == (d2.result.score <= 0.5).tolist()


def test_sequence_rules_are_left_out_with_the_reason():
    rng = np.random.default_rng(1)
    db = _unit(rng.normal(size=(30, 8)))
    q = _unit(rng.normal(size=(20, 8)))
    s = q @ db.T
    hard = np.zeros_like(s, dtype=bool)
    hard[np.arange(20), np.arange(20)] = True
    bench = run_bench(s, db, hard, labels=np.repeat(np.arange(10), 3), sequence="the queries are not one route")
    for rule in RULES:
        if rule.needs == "sequence":
            assert bench.left_out[rule.key] == "the queries are not one route"
            assert rule.key not in bench.decisions
    assert "sue" in bench.left_out and "positions" in bench.left_out["sue"]
    assert {"baseline", "per-place", "pa-ratio"} <= set(bench.decisions)


def test_natural_open_set_refuses_an_unordered_database_and_bad_shares():
    s = np.zeros((4, 10), dtype=np.float32)
    with pytest.raises(VPRInputError, match="not one route"):
        natural_open_set(s, np.eye(10, dtype=np.float32), np.eye(4, 10, dtype=bool), labels=None, sequence=None,
                         ordered=False)
    for share in (0.0, 1.0, 1.5, float("nan")):
        with pytest.raises(VPRInputError, match="reference_share"):
            BenchOptions(reference_share=share)
    with pytest.raises(VPRInputError, match="keeps 1 of 10"):
        natural_open_set(s, np.eye(10, dtype=np.float32), np.eye(4, 10, dtype=bool), labels=None, sequence=None,
                         ordered=True, options=BenchOptions(reference_share=0.15))


def test_options_refuse_what_does_not_apply():
    with pytest.raises(VPRInputError, match="only rules with a free τ"):
        BenchOptions(taus={"per-place": 0.5})
    with pytest.raises(VPRInputError, match="rules="):
        BenchOptions(rules=("per-place", "nonsense"))
    with pytest.raises(VPRInputError, match="place_score"):
        BenchOptions(place_score="median")
    with pytest.raises(VPRInputError, match="fanout"):
        BenchOptions(fanout=0)


def test_recall_at_k_counts_rejection():
    s = np.array([[0.9, 0.8, 0.1], [0.2, 0.9, 0.8]], dtype=np.float32)
    db = _unit(np.eye(3, 4))
    hard = np.array([[0, 1, 0], [0, 0, 1]], dtype=bool)
    bench = run_bench(s, db, hard, labels=None, sequence="x",
                      options=BenchOptions(rules=("baseline", "top1-distance"), ks=(1, 2),
                                           taus={"top1-distance": float(np.sqrt(2 - 2 * 0.9)) - 1e-3}))
    assert bench.recall["baseline"] == {1: 0.0, 2: 100.0}
    # top-1 distance √(2 − 1.8) ≈ 0.447 > τ: both rejected, so no recall at any K
    assert bench.recall["top1-distance"] == {1: 0.0, 2: 0.0}


def test_sue_reads_metres_only(gp_left_right):
    value, _ = gp_left_right
    xy, why = metres_positions(value)
    assert xy is None and "not metres" in why  # gp_pos.csv is the unit square


def test_report_renders_and_is_strict_json(gp_left_right):
    value, d = gp_left_right
    labels, _ = retrieval_places(value, PlaceSpec(3, 10))
    report = acceptance_report(value, d, labels=labels)
    text = render_report(report)
    for rule in RULES:
        if rule.key in report.closed.decisions:
            assert rule.label in text
    assert "sue left out" in text
    data = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert data["closed_set"]["rules"]["baseline"]["F1"] == pytest.approx(report.closed.counts["baseline"].f1)
    assert data["natural_open_set"]["n_distractor"] == 60


def test_a_query_just_past_the_cut_is_a_distractor_even_with_a_kept_image_within_tolerance(gardens_point, gp_pixels):
    """Day_left queries against day_right: query 140's images 138–139 (±2) are kept, its own frame is cut."""
    value = database_queries(gardens_point, "day_left", database=["day_right"], tolerance=2)
    rows = value_rows(value)
    d = np.asarray(gp_pixels if rows is None else gp_pixels[rows], dtype=np.float32)
    report = acceptance_report(value, d, labels=retrieval_places(value, PlaceSpec(3, 10))[0])
    assert report.natural is not None, report.natural_note
    assert not report.natural.genuine[140] and report.natural.genuine[139]
    hard = value.ground_truth.dense()
    assert hard[140, 138] and hard[140, 139]
    for key, dec in report.natural.decisions.items():
        c = report.natural.counts[key]
        assert c.n_genuine == 140 and c.n_distractor == 60
        # an accepted distractor is a false positive whatever image it names
        assert c.tn == int((~dec.accepted[140:]).sum()), key


def test_discovered_places_need_a_database_route(data_root, tmp_path):
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts
    from vpr_explorer.pipeline import dataset_descriptors, open_dataset

    paths = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path)
    ds = open_dataset(paths["database-queries"], "database-queries")
    assert not ds.ordered
    d = dataset_descriptors(ds, "pixels")
    with pytest.raises(VPRInputError, match="places=discovered"):
        acceptance_report(ds, d, labels=None, options=BenchOptions(places="discovered"))
