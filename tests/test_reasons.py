"""Each acceptance rule's reasons for one query (``views.reasons``): sentences and figures against the bench's
numbers and plain-loop references, on GardensPoint night_right vs day_right and on hand-made matrices."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.match_scores import SUE_CLIP_M, SUE_K, SUE_SLOPE, sue
from vpr_explorer.method.places import PlaceSpec, retrieval_places
from vpr_explorer.method.retrieval import similarity
from vpr_explorer.method.sequences import VELOCITIES
from vpr_explorer.protocols.acceptance import (
    RULES,
    AcceptanceReport,
    BenchOptions,
    acceptance_report,
    run_bench,
)
from vpr_explorer.views import reasons as why

GATED = ("seqslam", "top1-distance", "pa-ratio", "sue")  # accepted ⇔ score ≤ τ


# --------------------------------------------------------------------------- GardensPoint


@pytest.fixture(scope="module")
def gp(gardens_point, gp_pixels):
    """The bench on night_right queries against day_right (right within ±2 frames), places group 3, step 10."""
    value = database_queries(gardens_point, "night_right", database=["day_right"], tolerance=2)
    d = gp_pixels[value_rows(value)]
    labels, _ = retrieval_places(value, PlaceSpec(3, 10))
    report = acceptance_report(value, d, labels=labels)
    s = similarity(d[value.n_database:], d[:value.n_database])
    return value, d, report, s


def reasons_of(gp, q):
    value, d, report, s = gp
    return {r.key: r for r in why.rule_reasons(report, q, s[q], value.ground_truth.positives(q))}


def test_one_reason_per_rule_in_order_and_the_left_out_say_why(gp):
    value, d, report, s = gp
    reasons = why.rule_reasons(report, 57, s[57], value.ground_truth.positives(57))
    assert [r.key for r in reasons] == [r.key for r in RULES]
    assert [r.label for r in reasons] == [r.label for r in RULES]
    sue_reason = reasons[-1]
    assert sue_reason.status is why.Status.LEFT_OUT and sue_reason.image == -1 and sue_reason.right is None
    note = next(n for n in report.notes if n.startswith("sue left out: "))
    assert sue_reason.sentence == "left out: " + note[len("sue left out: "):]  # the note's metres reason
    assert sue_reason.text == f"{sue_reason.label}: {sue_reason.sentence}"


def test_status_image_and_right_follow_every_decision(gp):
    """Every query, every rule: a plain reading of ``RuleDecisions`` and the ground truth."""
    value, d, report, s = gp
    hard = value.ground_truth.dense()
    graph = report.closed.decisions["per-query-graph"].result[0]
    for q in range(value.n_queries):
        reasons = reasons_of(gp, q)
        for key, dec in report.closed.decisions.items():
            r = reasons[key]
            if dec.accepted[q]:
                assert r.status is why.Status.ACCEPTED and r.image == dec.answer[q]
                assert r.sentence.startswith(f"accepted image {r.image} ")
            else:
                expected = graph.path[q] if key == "per-query-graph" else dec.candidate[q]
                assert r.status is why.Status.REJECTED and r.image == expected, (key, q)
                assert r.sentence.startswith("rejected")
            if r.image >= 0:
                assert r.right == hard[q, r.image]
                assert f"image {r.image} ({'right' if r.right else 'wrong'})" in r.sentence
            else:
                assert r.right is None


def test_the_comparison_sign_is_the_decision(gp):
    value, d, report, s = gp
    seen = set()
    for q in range(value.n_queries):
        reasons = reasons_of(gp, q)
        for key, dec in report.closed.decisions.items():
            text, accepted = reasons[key].sentence, bool(dec.accepted[q])
            if key in GATED:
                if key == "seqslam" and dec.candidate[q] < 0:
                    assert "no centred trajectory" in text
                    continue
                assert ("≤ τ" in text) == accepted and ("> τ" in text) == (not accepted), (key, q, text)
            elif key in ("per-place", "per-place-k", "sequence-per-place"):
                if dec.detail["place"][q] < 0:
                    assert "no place has a score" in text
                    continue
                assert ("≥ its θ" in text) == accepted and ("< its θ" in text) == (not accepted), (key, q, text)
            elif key == "per-query":
                assert ("≥ the smoothed threshold" in text) == accepted, (q, text)
            elif key == "per-query-graph":
                assert ("< C_nm" in text) == accepted and ("≥ C_nm" in text) == (not accepted), (q, text)
                assert text.endswith("a hidden node") == (not accepted)
            seen.add((key, accepted))
    # the data exercise both outcomes of the rules that reject here
    for key in ("per-place-k", "per-query", "per-query-graph", "seqslam", "top1-distance"):
        assert {(key, True), (key, False)} <= seen, key


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"-?\d+\.\d+", text)]


def test_per_query_sentence_gives_threshold_test_and_where_theta_comes_from(gp):
    value, d, report, s = gp
    qt = report.closed.decisions["per-query"].result
    bimodal = np.flatnonzero(qt.bimodal)
    measured_before = None
    for q in range(value.n_queries):
        text = reasons_of(gp, q)["per-query"].sentence
        assert f"its score {qt.top_score[q]:.3f}" in text or f"its score {qt.top_score[q]:.4f}" in text
        if qt.bimodal[q]:
            assert "patch bimodal" in text and f"boundary {qt.raw_threshold[q]:.3f}" in text
            measured_before = q
        elif measured_before is None:  # plain reference: no measurement yet, the patch mean
            assert "no measurement yet" in text and f"patch mean {qt.patch_mean[q]:.3f}" in text
            assert qt.threshold[q] == qt.patch_mean[q]
        else:
            assert f"held since query {measured_before}" in text, (q, text)
    assert 0 < len(bimodal) < value.n_queries


def test_graph_sentence_gives_node_cost_and_the_non_matching_cost(gp):
    value, d, report, s = gp
    match, qt = report.closed.decisions["per-query-graph"].result
    for q in (int(np.flatnonzero(match.hidden)[0]), int(np.flatnonzero(~match.hidden)[0])):
        text = reasons_of(gp, q)["per-query-graph"].sentence
        cost = 1.0 - float(s[q, match.path[q]])
        assert _numbers(text)[0] == pytest.approx(cost, abs=1e-3)
        assert f"C_nm {match.non_matching_cost:.3f}" in text
        assert f"median per-query threshold {float(np.median(qt.threshold)):.3f}" in text


def test_seqslam_sentence_gives_ratio_velocity_and_the_best_outside_the_window(gp):
    value, d, report, s = gp
    dec = report.closed.decisions["seqslam"]
    res = dec.result
    for q in (50, 120, 3):
        text = reasons_of(gp, q)["seqslam"].sentence
        if res.match[q] < 0:
            assert "ds/2 = 5 queries" in text
            continue
        m = int(res.match[q])
        outside = [(res.scores[q, j], j) for j in range(value.n_database) if abs(j - m) > 5]
        second, j2 = min(outside)  # plain loop: lowest score, lowest index on a tie
        assert why.seqslam_competitor(res, q) == (j2, second)
        assert res.ratio[q] == pytest.approx(res.score[q] / second)
        assert f"(image {j2}) {second:.4g}" in text and f"velocity {res.velocity[q]:.1f}" in text
        assert f"ratio {res.ratio[q]:.4f}" in text or f"ratio {res.ratio[q]:.5f}" in text
        assert "(oracle)" in text


def test_pa_ratio_sentence_gives_the_two_distances(gp):
    value, d, report, s = gp
    u = report.closed.decisions["pa-ratio"].detail["score"]
    for q in (0, 57, 150):
        row = s[q].astype(np.float64)
        order = sorted(range(len(row)), key=lambda j: (-row[j], j))  # plain reference
        d1, d2 = math.sqrt(max(0.0, 2 - 2 * row[order[0]])), math.sqrt(max(0.0, 2 - 2 * row[order[1]]))
        text = reasons_of(gp, q)["pa-ratio"].sentence
        assert f"d₁/d₂ = {d1:.3f}/{d2:.3f}" in text
        assert d1 / d2 == pytest.approx(u[q], abs=1e-6)
        two = why.nearest_two(s[q])
        assert two.images.tolist() == order[:2] and not two.tie


def test_place_sentence_names_the_place_and_its_threshold(gp):
    value, d, report, s = gp
    for key, symbol in (("per-place", "θ_p"), ("per-place-k", "θ_k")):
        dec = report.closed.decisions[key]
        queries = [int(np.flatnonzero(dec.accepted == a)[0]) for a in (True, False) if (dec.accepted == a).any()]
        assert len(queries) == (1 if key == "per-place" else 2)  # per-place accepts every query here
        for q in queries:
            text = reasons_of(gp, q)[key].sentence
            p = int(dec.detail["place"][q])
            assert f"P{p}" in text and f"its {symbol} " in text
            raw, theta = _numbers(text.split(f"P{p}")[1])[:2]
            assert raw == pytest.approx(dec.detail["raw"][q], abs=1e-3)
            assert theta == pytest.approx(dec.detail["theta"][q], abs=1e-3)
            assert report.closed.places[dec.candidate[q]] == p  # the image answered lies in that place


def test_bad_queries_and_rows_are_refused(gp):
    value, d, report, s = gp
    for q in (-1, value.n_queries, 2.0, True):
        with pytest.raises(VPRInputError, match="query="):
            why.rule_reasons(report, q, s[0], [])
    with pytest.raises(VPRInputError, match="row of shape"):
        why.rule_reasons(report, 0, s[0, :10], [])
    with pytest.raises(VPRInputError, match="queries 0 to 199"):
        why.neighbourhood(d, value.n_database, 190, 201)
    with pytest.raises(VPRInputError, match="database rows first"):
        why.neighbourhood(d[0], value.n_database, 0, 1)


# --------------------------------------------------------------------------- the similarity rows


def test_reason_rows_cover_every_figure_and_stop_at_the_ends(gp):
    value, d, report, s = gp
    qt = report.closed.decisions["per-query"].result
    assert why.reason_rows(report, 100) == (min(100 - why.GRAPH_HALF, int(qt.patch_rows[100, 0])), 111)
    assert why.reason_rows(report, 0) == (0, why.GRAPH_HALF + 1)
    assert why.reason_rows(report, 199) == (int(qt.patch_rows[199, 0]), 200)


def test_neighbourhood_rows_are_the_similarity_matrix_rows(gp):
    value, d, report, s = gp
    nb = why.neighbourhood(d, value.n_database, 81, 111)
    assert nb.similarity.shape == (30, 200) and nb.stop == 111 and not nb.similarity.flags.writeable
    np.testing.assert_allclose(nb.similarity, s[81:111], atol=1e-6)
    np.testing.assert_allclose(nb.row(100), s[100], atol=1e-6)
    with pytest.raises(VPRInputError, match="holds 81 to 110"):
        nb.rows(80, 90)


# --------------------------------------------------------------------------- figures


def trace(fig, meta: str) -> dict:
    found = [t for t in fig.data if t.meta == meta]
    assert len(found) == 1, [t.meta for t in fig.data]
    return found[0]


def test_patch_figure_is_the_patch_its_histogram_mixture_and_thresholds(gp):
    value, d, report, s = gp
    qt = report.closed.decisions["per-query"].result
    for q in (int(np.flatnonzero(qt.bimodal)[0]), 100):
        a, b = why.reason_rows(report, q)
        fig = why.patch_figure(why.neighbourhood(d, value.n_database, a, b), qt, q)
        (r0, r1), (c0, c1) = qt.patch_rows[q], qt.patch_cols[q]
        patch = trace(fig, "patch")
        np.testing.assert_allclose(patch.z, s[r0:r1, c0:c1], atol=1e-6)
        assert list(patch.x) == list(range(c0, c1)) and list(patch.y) == list(range(r0, r1))
        assert (trace(fig, "best match").x[0], trace(fig, "best match").y[0]) == (qt.best_match[q], q)
        assert np.mean(patch.z) == pytest.approx(qt.patch_mean[q], abs=1e-6)
        bars = trace(fig, "values")
        assert np.sum(np.asarray(bars.y) * np.asarray(bars.width)) == pytest.approx(1.0)
        assert trace(fig, "threshold").x[0] == qt.threshold[q]
        assert trace(fig, "score").x[0] == qt.top_score[q]
        metas = [t.meta for t in fig.data]
        if qt.bimodal[q]:
            assert trace(fig, "boundary").x[0] == qt.raw_threshold[q]
            for k in range(2):
                c = trace(fig, f"component {k}")
                x = np.asarray(c.x)
                w, mu, sd = qt.weights[q, k], qt.means[q, k], qt.stds[q, k]
                expected = [w * math.exp(-0.5 * ((v - mu) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)) for v in x]
                np.testing.assert_allclose(c.y, expected, rtol=1e-9)
        else:
            assert "boundary" not in metas and "component 0" not in metas


def ref_velocity(block_similarity: np.ndarray, j: int, ds: int = 10, r: int = 10) -> tuple[int, float]:
    """Plain loop: the centre row's best velocity at image j on ds + 1 rows (each row enhanced on its own)."""
    dd = 1.0 - block_similarity.astype(np.float64)
    nq, nd = dd.shape
    e = np.zeros_like(dd)
    for q in range(nq):
        for c in range(nd):
            w = dd[q, max(0, c - r // 2):min(nd - 1, c + r // 2) + 1]
            sd = np.std(w, ddof=1)
            e[q, c] = 0.0 if sd <= 1e-9 * (1 + abs(np.mean(w))) else (dd[q, c] - np.mean(w)) / sd
    sums = []
    for v in VELOCITIES:
        cols = [j - ds // 2 + math.floor(k * v + 1e-9) for k in range(ds + 1)]
        sums.append(math.inf if cols[-1] >= nd else sum(e[k, c] for k, c in enumerate(cols)))
    order = np.argsort(sums, kind="stable")
    return int(order[0]), sums[order[1]] - sums[order[0]]


def test_seqslam_trajectories_are_the_best_and_the_best_competitor(gp):
    value, d, report, s = gp
    res = report.closed.decisions["seqslam"].result
    checked = 0
    for q in range(5, 195, 7):
        a, b = why.reason_rows(report, q)
        nb = why.neighbourhood(d, value.n_database, a, b)
        best, other = why.seqslam_trajectories(nb, res, q, ds=10)
        m = int(res.match[q])
        assert best.image == m and best.velocity == res.velocity[q] and best.score == res.score[q]
        assert best.rows.tolist() == list(range(q - 5, q + 6))
        assert best.columns.tolist() == [m - 5 + math.floor(k * best.velocity + 1e-9) for k in range(11)]
        j2, second = why.seqslam_competitor(res, q)
        assert (other.image, other.score) == (j2, second) and abs(j2 - m) > 5
        block = s[q - 5:q + 6]
        for t in (best, other):
            k, gap = ref_velocity(block, t.image)
            if gap > 1e-6:  # velocities that tie to rounding may go either way
                assert t.velocity == VELOCITIES[k], (q, t.image)
                checked += 1
            assert t.columns.tolist() == [t.image - 5 + math.floor(i * t.velocity + 1e-9) for i in range(11)]
        fig = why.seqslam_figure(nb, best, other, q)
        line = trace(fig, "best trajectory")
        assert list(line.x) == best.columns.tolist() and list(line.y) == best.rows.tolist()
        assert list(trace(fig, "competitor trajectory").x) == other.columns.tolist()
        edges = trace(fig, "ratio window").x
        assert (edges[0], edges[3]) == (m - 5.5, m + 5.5)
        heat = [t for t in fig.data if t.meta == "similarity"]
        assert len(heat) == 2
        pad = why.COLUMN_PAD
        for h, lo, hi in ((heat[0], min(best.columns.min(), m - 5), max(best.columns.max(), m + 5)),
                          (heat[1], other.columns.min(), other.columns.max())):
            assert list(h.x) == list(range(max(0, lo - pad), min(200, hi + pad + 1)))
            np.testing.assert_allclose(h.z, s[q - 5:q + 6][:, np.asarray(h.x)], atol=1e-6)
    assert checked > 20
    with pytest.raises(VPRInputError, match="no centred trajectory"):
        why.seqslam_trajectories(why.neighbourhood(d, value.n_database, 0, 11), res, 2, ds=10)


def test_graph_figure_draws_the_path_and_marks_hidden_nodes(gp):
    value, d, report, s = gp
    match = report.closed.decisions["per-query-graph"].result[0]
    q = int(np.flatnonzero(match.hidden)[0])
    a, b = why.reason_rows(report, q)
    fig = why.graph_figure(why.neighbourhood(d, value.n_database, a, b), match, q)
    r0, r1 = max(0, q - why.GRAPH_HALF), min(200, q + why.GRAPH_HALF + 1)
    path = trace(fig, "path")
    assert list(path.x) == match.path[r0:r1].tolist() and list(path.y) == list(range(r0, r1))
    hidden = [(int(match.path[i]), i) for i in range(r0, r1) if match.matched[i] < 0]  # plain loop
    matched = [(int(match.path[i]), i) for i in range(r0, r1) if match.matched[i] >= 0]
    assert list(zip(trace(fig, "hidden").x, trace(fig, "hidden").y)) == hidden and hidden
    assert list(zip(trace(fig, "matched").x, trace(fig, "matched").y)) == matched
    assert (trace(fig, "query node").x[0], trace(fig, "query node").y[0]) == (match.path[q], q)
    heat = trace(fig, "similarity")
    np.testing.assert_allclose(heat.z, s[r0:r1][:, np.asarray(heat.x)], atol=1e-6)
    assert min(heat.x) == max(0, match.path[r0:r1].min() - why.COLUMN_PAD)


# --------------------------------------------------------------------------- hand-made matrices


@pytest.fixture(scope="module")
def small():
    """30 queries × 40 database images on a 10 m route; query q is right at database images q − 1 … q + 1."""
    rng = np.random.default_rng(7)
    db = rng.normal(size=(40, 16))
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    queries = db[:30] + 0.6 * rng.normal(size=(30, 16))
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    s = similarity(queries, db)
    hard = np.abs(np.arange(30)[:, None] - np.arange(40)[None, :]) <= 1
    xy = np.stack([np.arange(40) * 10.0, np.zeros(40)], axis=1)
    return s, db, hard, xy


def small_report(small, **taus) -> AcceptanceReport:
    s, db, hard, xy = small
    bench = run_bench(s, db, hard, labels=np.arange(40) // 4, sequence=None, database_xy=xy,
                      options=BenchOptions(taus=taus))
    return AcceptanceReport(bench, None, "", {"ds": 10, "fanout": 5, "place_score": "best"}, ())


def test_nearest_two_hand_cases():
    two = why.nearest_two(np.array([0.1, 0.9, 0.5, 0.2]))
    assert two.images.tolist() == [1, 2] and not two.tie
    np.testing.assert_allclose(two.distances, [math.sqrt(0.2), 1.0])
    tie = why.nearest_two(np.array([0.1, 0.5, 0.5, 0.2]))
    assert tie.images.tolist() == [1, 2] and tie.tie  # an exact tie: the lower index first
    one = why.nearest_two(np.array([0.3]))
    assert one.images.tolist() == [0] and not one.tie


def test_a_tie_of_the_two_nearest_says_u_is_one(small):
    s, db, hard, xy = small
    s = s.copy()
    s[4, 9] = s[4].max()  # a second image at the top similarity
    report = small_report((s, db, hard, xy))
    r = {x.key: x for x in why.rule_reasons(report, 4, s[4], np.flatnonzero(hard[4]))}
    assert "its two nearest images tie" in r["pa-ratio"].sentence and "counts as 1.0000" in r["pa-ratio"].sentence


def test_a_tau_close_to_the_score_gets_the_decimals_that_tell_them_apart(small):
    s, db, hard, xy = small
    u = run_bench(s, db, hard, labels=None, sequence=None).decisions["pa-ratio"].detail["score"]
    q = int(np.argmax(u < 0.99))
    tau = float(u[q]) - 3e-6  # equal to 4 decimals
    report = small_report(small, **{"pa-ratio": tau})
    r = {x.key: x for x in why.rule_reasons(report, q, s[q], np.flatnonzero(hard[q]))}
    text = r["pa-ratio"].sentence
    assert r["pa-ratio"].status is why.Status.REJECTED and "(given)" in text
    shown_u, shown_tau = re.search(r"= (\d\.\d+) > τ (\d\.\d+)", text).groups()
    assert shown_u != shown_tau and len(shown_u) == len(shown_tau) <= 2 + why.MAX_DIGITS
    assert float(shown_u) == pytest.approx(u[q], abs=10 ** -(len(shown_u) - 2))
    report = small_report(small, **{"pa-ratio": float(u[q])})  # exactly at τ: accepted, equal numbers
    r = {x.key: x for x in why.rule_reasons(report, q, s[q], np.flatnonzero(hard[q]))}
    assert r["pa-ratio"].status is why.Status.ACCEPTED
    assert re.search(r"= (\d\.\d{4}) ≤ τ \1 \(given\)", r["pa-ratio"].sentence)


def ref_sue(row, xy, k=SUE_K, slope=SUE_SLOPE, clip=SUE_CLIP_M):
    """Plain loop from the SUE definition: softmax of −slope·d over the top K, weighted mean, clipped spread."""
    top = sorted(range(len(row)), key=lambda j: (-row[j], j))[:k]
    d = [math.sqrt(max(0.0, 2 - 2 * row[j])) for j in top]
    e = [math.exp(-slope * (x - min(d))) for x in d]
    w = [x / sum(e) for x in e]
    mean = [sum(wi * xy[j, a] for wi, j in zip(w, top)) for a in range(2)]
    spread = 0.5 * sum(wi * sum(min(clip, max(-clip, xy[j, a] - mean[a])) ** 2 for a in range(2))
                       for wi, j in zip(w, top))
    return top, w, mean, spread


def test_sue_weights_and_map_against_the_definition(small):
    s, db, hard, xy = small
    report = small_report(small)
    for q in (0, 12, 29):
        row = s[q].astype(np.float64)
        top, w, mean, spread = ref_sue(row, xy)
        got = why.sue_weights(s[q], xy)
        assert got.images.tolist() == top
        np.testing.assert_allclose(got.weights, w, rtol=1e-9)
        np.testing.assert_allclose(got.centre, mean, atol=1e-9)
        assert got.score == pytest.approx(spread, rel=1e-9)
        assert got.score == pytest.approx(sue(s[q:q + 1], xy).score[0], rel=1e-9)
        assert got.score == pytest.approx(report.closed.decisions["sue"].detail["score"][q], rel=1e-6)

        class Value:  # what sue_map reads of a dataset value
            database_xy, query_xy = xy, xy[:30] + [0.0, 5.0]

        fig = why.sue_map(Value, report.closed.places, q, got)
        origin = np.floor(np.vstack([xy, Value.query_xy]).min(axis=0) / 100.0) * 100.0
        dots = trace(fig, "top-K")
        np.testing.assert_allclose(np.stack([dots.x, dots.y], axis=1), xy[top] - origin)
        np.testing.assert_allclose(np.asarray(dots.customdata)[:, 1], w, rtol=1e-9)
        assert np.argmax(dots.marker.size) == int(np.argmax(w))
        np.testing.assert_allclose([trace(fig, "weighted mean").x[0], trace(fig, "weighted mean").y[0]],
                                   np.asarray(mean) - origin, atol=1e-9)
        assert trace(fig, "selected query").customdata[0] == q
    r = {x.key: x for x in why.rule_reasons(report, 12, s[12], np.flatnonzero(hard[12]))}
    assert "SUE" in r["sue"].sentence and "m²" in r["sue"].sentence and "top-10" in r["sue"].sentence
    with pytest.raises(VPRInputError, match="database_xy"):
        why.sue_weights(s[0], xy[:5])


def test_hand_made_sequence_rules_run_and_explain_every_query(small):
    """The hand-made route is one sequence (``sequence=None``): every rule explains every query."""
    s, db, hard, xy = small
    report = small_report(small)
    assert not report.closed.left_out
    for q in range(30):
        reasons = why.rule_reasons(report, q, s[q], np.flatnonzero(hard[q]))
        assert [r.key for r in reasons] == [r.key for r in RULES]
        assert all(r.status is not why.Status.LEFT_OUT for r in reasons)
