"""Protocols against a loop reference over the same splits, and on real GardensPoint."""

import numpy as np
import pytest

from reference import loop_protocol, loop_rank, loop_thresholds, pairwise_negative_stats, synthetic_places
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import (
    draw_splits,
    oracle_global_threshold,
    open_set_protocol,
    paper_protocol,
    retrieval_protocol,
    run_split,
)
from vpr_explorer.protocols.options import RUNS, ProtocolOptions
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.method.retrieval import similarity


def _synthetic(seed=0, n_places=12, per_place=6, dim=32, noise=0.9, n_trav=3):
    """Places with a shared centre plus noise (``reference.synthetic_places``)."""
    return synthetic_places(seed, n_places, per_place, dim, noise, n_trav)


def _reference_recall(d, labels, trav, n_places, splits, rule, theta_name, ks=(1, 3, 5, 10)):
    """Loops: thresholds from training only, raw_p per place, pessimistic ranks."""
    per_split = []
    for sp in splits:
        tr, q = sp.train, sp.queries
        mu, sigma = pairwise_negative_stats(d[tr], labels[tr])
        n_neg = np.array([np.sum(labels[tr] != labels[i]) for i in tr])
        simple, weighted = loop_thresholds(mu, sigma, n_neg, labels[tr], n_places)
        theta = {"simple": simple, "weighted": weighted}.get(theta_name)
        scores = np.full((len(q), n_places), -np.inf)
        for a, qi in enumerate(q):
            for p in range(n_places):
                members = [j for j in tr if labels[j] == p]
                if not members:
                    continue
                raw = max(float(d[qi] @ d[j]) for j in members)
                if rule == "none":
                    scores[a, p] = raw
                elif raw >= theta[p]:
                    scores[a, p] = raw - theta[p] if rule == "margin" else raw
        correct = np.zeros_like(scores, dtype=bool)
        known = ~sp.unknown[labels[q]]
        correct[np.flatnonzero(known), labels[q][known]] = True
        ranks = loop_rank(scores, correct)[known]
        per_split.append([np.mean(ranks <= k) for k in ks])
    return np.mean(per_split, axis=0), np.std(per_split, axis=0)


@pytest.mark.parametrize("key, rule, theta", [
    ("place-baseline", "none", None), ("margin-simple", "margin", "simple"),
    ("margin-weighted", "margin", "weighted"), ("raw-weighted", "raw", "weighted"),
])
def test_paper_protocol_equals_loop_reference(key, rule, theta):
    d, labels, trav = _synthetic()
    ev = paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=6, seed=3))
    splits = draw_splits(labels, 12, runs=6, seed=3)
    mean, std = _reference_recall(d, labels, trav, 12, splits, rule, theta)
    row = ev.row(key)
    np.testing.assert_allclose([row.recall[k][0] for k in ev.ks], mean, atol=1e-12)
    np.testing.assert_allclose([row.recall[k][1] for k in ev.ks], std, atol=1e-12)


def test_open_set_known_recall_equals_loop_reference():
    d, labels, trav = _synthetic(seed=1)
    ev = open_set_protocol(d, labels, trav, 12, ProtocolOptions(runs=5, seed=2, unknown_share=0.25, k_grid=(0.0, 1.0)))
    splits = draw_splits(labels, 12, runs=5, seed=2, unknown_share=0.25)
    assert all(sp.unknown.sum() == 3 for sp in splits)
    mean, _ = _reference_recall(d, labels, trav, 12, splits, "margin", "weighted")
    assert ev.row("margin-weighted").recall[1][0] == pytest.approx(mean[0])
    k0 = next(t for t in ev.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "margin" and t.param == 0.0)
    assert k0.known_recall1[0] == pytest.approx(mean[0])


def test_splits_hold_out_one_query_per_place_and_never_train_on_it():
    labels = np.r_[np.repeat(np.arange(5), 4), [-1, -1]]
    for sp in draw_splits(labels, 5, runs=10, seed=0):
        assert sorted(labels[sp.queries]) == [0, 1, 2, 3, 4]
        assert not set(sp.queries) & set(sp.train)
        assert len(sp.train) == 15 and (labels[sp.train] >= 0).all()
    a = draw_splits(labels, 5, runs=3, seed=7)
    b = draw_splits(labels, 5, runs=3, seed=7)
    assert all(np.array_equal(x.queries, y.queries) for x, y in zip(a, b))
    c = draw_splits(labels, 5, runs=3, seed=8)
    assert any(not np.array_equal(x.queries, y.queries) for x, y in zip(a, c))


@pytest.mark.parametrize("field, value, fragments", [
    ("seed", -1, ["seed=-1", "0 or more"]),
    ("seed", 2**63, [f"seed={2**63}", "or less"]),
    ("seed", 1.5, ["seed=1.5", "whole number"]),
    ("runs", 0, ["runs=0", "1 or more"]),
    ("runs", 1001, ["runs=1001", "1,000 or less", f"the paper uses {RUNS}"]),
    ("unknown_share", 1.5, ["unknown_share=1.5", "between 0 and 1"]),
    ("k_grid", (), ["k: give at least one value"]),
    ("k_grid", (0.0, float("nan")), ["k=nan", "finite"]),
    ("ks", (1, 0), ["ks=0", "K >= 1"]),
    ("user_theta", float("inf"), ["theta=inf", "finite"]),
    ("tolerance", -1, ["tolerance=-1", "0 or more"]),
    ("block", 0, ["block=0", "1 or more"]),
    ("threads", 0, ["threads=0", "1 or more"]),
])
def test_options_are_checked_once_when_made_naming_the_field(field, value, fragments):
    with pytest.raises(VPRInputError) as err:
        ProtocolOptions(**{field: value})
    assert all(f in str(err.value) for f in fragments), str(err.value)


def test_options_read_back_in_their_normal_form():
    o = ProtocolOptions(k_grid=[0, 1], ks=[1, 5], database="day", user_theta=1, threads=None)
    assert (o.k_grid, o.ks, o.database, o.user_theta) == ((0.0, 1.0), (1, 5), ("day",), 1.0)
    assert isinstance(o.threads, int) and o.threads >= 1
    assert o == ProtocolOptions(k_grid=(0.0, 1.0), ks=(1, 5), database=("day",), user_theta=1.0, threads=o.threads)
    assert ProtocolOptions().runs == RUNS == 50  # the paper's R
    hash(o)  # a cache key


def test_unknown_places_leave_training_entirely():
    labels = np.repeat(np.arange(10), 3)
    for sp in draw_splits(labels, 10, runs=5, seed=0, unknown_share=0.3):
        assert sp.unknown.sum() == 3
        assert not sp.unknown[labels[sp.train]].any()
        assert len(sp.queries) == 10


def test_thresholds_come_from_training_only():
    d, labels, trav = _synthetic(seed=2)
    sp = draw_splits(labels, 12, runs=1, seed=0)[0]
    tr, q = sp.train, sp.queries
    correct = np.zeros((len(q), 12), dtype=bool)
    correct[np.arange(len(q)), labels[q]] = True
    s = run_split(d[tr], labels[tr], trav[tr], similarity(d[q], d[tr]), correct, trav[q], 12)
    mu, sigma = pairwise_negative_stats(d[tr], labels[tr])
    n_neg = np.array([np.sum(labels[tr] != labels[i]) for i in tr])
    simple, weighted = loop_thresholds(mu, sigma, n_neg, labels[tr], 12)
    np.testing.assert_allclose(s.thresholds["simple"], simple, atol=1e-12)
    np.testing.assert_allclose(s.thresholds["weighted"], weighted, atol=1e-12)
    mu_all, _ = pairwise_negative_stats(d[labels >= 0], labels)
    assert not np.allclose(s.thresholds["simple"], loop_thresholds(mu_all, mu_all, np.ones(len(d)), labels, 12)[0])


def test_cross_condition_never_matches_own_traversal():
    d, labels, trav = _synthetic(seed=3)
    ev = paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=5, seed=0, cross_condition=True))
    for r in ev.rows:
        if r.own_traversal is not None and not np.isnan(r.own_traversal[0]):
            assert r.own_traversal[0] == 0.0
    plain = paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=5, seed=0))
    assert plain.row("place-baseline").own_traversal[0] > 0


def test_oracle_global_threshold_hand_case():
    top = np.array([0.9, 0.8, 0.7, 0.6])
    right = np.array([True, False, True, True])
    known = np.array([True, True, True, False])
    # θ=0.7: accepts 0.9 (right), 0.8 (wrong), 0.7 (right), rejects 0.6 (unknown: right) -> 3 of 4
    assert oracle_global_threshold(top, right, known) == 0.7
    # everything unknown: reject all
    assert oracle_global_threshold(top, right, np.zeros(4, bool)) > 0.9


def test_open_set_tradeoff_is_monotone_in_k():
    d, labels, trav = _synthetic(seed=4, noise=1.2)
    ev = open_set_protocol(d, labels, trav, 12, ProtocolOptions(runs=8, seed=0, k_grid=(-1, 0, 1, 2, 3)))
    rows = [t for t in ev.tradeoff if t.series == "θ_p(k) weighted" and t.rule == "margin"]
    rejection = [t.unknown_rejection[0] for t in rows]
    accepted = [t.accepted[0] for t in rows]
    assert rejection == sorted(rejection) and accepted == sorted(accepted, reverse=True)
    assert rejection[-1] > rejection[0]


def test_bad_parameters():
    d, labels, trav = _synthetic()
    with pytest.raises(VPRInputError, match="runs=0"):
        paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=0))
    with pytest.raises(VPRInputError, match="unknown_share=1.5"):
        open_set_protocol(d, labels, trav, 12, ProtocolOptions(runs=1, unknown_share=1.5))
    single = np.arange(12)  # one image per place
    with pytest.raises(VPRInputError, match="have a single image"):
        paper_protocol(d[:12], single, trav[:12], 12, ProtocolOptions(runs=1))
    with pytest.raises(VPRInputError, match="3 rows"):
        paper_protocol(d[:3], labels, trav, 12, ProtocolOptions(runs=1))
    with pytest.raises(VPRInputError, match="cross_condition needs at least 2 traversals"):
        paper_protocol(d, labels, np.zeros_like(trav), 12, ProtocolOptions(runs=1, cross_condition=True))


@pytest.mark.realdata
def test_gardens_point_paper_protocol_effnet(gardens_point, gp_effnet):
    places = make_places(gardens_point, PlaceSpec(3, 10))
    ev = paper_protocol(gp_effnet, places.image_place, gardens_point.image_traversal, places.n_places,
                        ProtocolOptions(runs=50))
    r1 = {r.key: r.recall[1][0] for r in ev.rows}
    print({k: round(v, 3) for k, v in r1.items()})
    assert ev.settings["queries_per_run"] == 20
    assert r1["place-baseline"] > 0.7
    # at R@1 the top image's place is the top place: image and place level agree
    assert r1["image-baseline"] == pytest.approx(r1["place-baseline"])
    # the raw rule with θ at the centre of the negatives drops almost nothing
    assert abs(r1["raw-weighted"] - r1["place-baseline"]) < 0.05


@pytest.mark.realdata
def test_gardens_point_traversal_protocol_effnet(gardens_point, gp_effnet):
    # every frame its own place, ±2 frames: the retrieval figure quoted for this descriptor (about 0.6)
    from vpr_explorer.pipeline import run_protocol

    places = make_places(gardens_point, PlaceSpec(1, 1))
    ev = run_protocol("traversal", gardens_point, places, gp_effnet,
                      ProtocolOptions(database=["day_right"], queries="night_right", tolerance=2))
    r1 = ev.row("image-baseline").recall[1][0]
    print("night_right -> day_right R@1 (±2):", r1)
    assert 0.45 < r1 < 0.8
    assert ev.settings["queries_scored"] == 200


@pytest.mark.realdata
@pytest.mark.parametrize("spec, tolerance, database", [
    (PlaceSpec(3, 10), 0, ("day_right",)), (PlaceSpec(3, 3), 2, ("day_left", "day_right")),
])
def test_the_traversal_protocol_is_the_database_queries_protocol_on_the_value(gardens_point, gp_pixels, spec,
                                                                              tolerance, database):
    """Its table is ``retrieval_protocol``'s on the value's rows; its settings name the traversals, as they did."""
    from vpr_explorer.data.aligned import database_queries, value_rows
    from vpr_explorer.pipeline import run_protocol

    places = make_places(gardens_point, spec)
    options = ProtocolOptions(database=database, queries="night_right", tolerance=tolerance)
    ev = run_protocol("traversal", gardens_point, places, gp_pixels, options)
    value = database_queries(gardens_point, query="night_right", database=database, tolerance=tolerance)
    rows = value_rows(value)
    d = gp_pixels if rows is None else gp_pixels[rows]
    want = retrieval_protocol(d[:value.n_database], d[value.n_database:], places.frame_place[value.database_frame],
                              places.n_places, value.ground_truth, options)
    assert ev.protocol.value == "traversal" and ev.same_numbers(want) and ev.notes == want.notes
    between = int(sum(places.frame_place[max(0, f - tolerance):f + tolerance + 1].max() < 0 for f in range(200)))
    assert {k: ev.settings[k] for k in ("database", "queries", "tolerance", "queries_scored",
                                        "queries_between_places")} == {
        "database": list(database), "queries": "night_right", "tolerance": tolerance,
        "queries_scored": 200 - between, "queries_between_places": between}
    assert "ground_truth" not in ev.settings and ev.settings["places"].endswith(")")


def test_to_dict_is_strict_json_when_nothing_is_accepted():
    import json

    d, labels, trav = _synthetic(seed=5)
    ev = open_set_protocol(d, labels, trav, 12, ProtocolOptions(runs=2, seed=0, user_theta=2.0, k_grid=(0.0,)))
    assert np.isnan(ev.row("global-user").precision[0])  # θ above every score: nothing accepted
    data = json.loads(json.dumps(ev.to_dict(), allow_nan=False))
    user = next(m for m in data["methods"] if m["key"] == "global-user")
    assert user["precision"] == {"mean": None, "std": None} and user["accepted"]["mean"] == 0.0
    adaptive = next(t for t in data["tradeoff"] if t["series"].startswith("adaptive"))
    assert adaptive["param"] is None


def test_same_numbers_compares_every_row_exactly_with_nan_equal_to_nan():
    import dataclasses

    d, labels, trav = _synthetic(seed=5)
    ev = paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=2, seed=0, user_theta=2.0))
    assert np.isnan(ev.row("global-user").precision[0])  # nothing accepted: NaN equals NaN
    again = paper_protocol(d, labels, trav, 12, ProtocolOptions(runs=2, seed=0, user_theta=2.0))
    assert ev.same_numbers(again)
    first = ev.rows[0]
    nudged = dataclasses.replace(first, recall={**first.recall, 1: (first.recall[1][0] + 1e-12, first.recall[1][1])})
    assert not ev.same_numbers(dataclasses.replace(ev, rows=(nudged, *ev.rows[1:])))
    assert not ev.same_numbers(dataclasses.replace(ev, rows=ev.rows[:-1]))


# --------------------------------------------------------------------------- frame tolerance in every protocol


def test_pooled_truth_hand_case_is_symmetric():
    from vpr_explorer.protocols.evaluation import pooled_truth

    # 9 frames, group 3 step 3: places [0,1,2] [3,4,5] [6,7,8]; one traversal, image i = frame i
    frame_place = np.repeat(np.arange(3), 3)
    image_place, image_frame = frame_place.copy(), np.arange(9)
    assert pooled_truth(image_place, image_frame, frame_place, 0, 3) is None
    img, place = pooled_truth(image_place, image_frame, frame_place, 1, 3)
    # frame 2 reaches frame 3 (place 1), frame 3 reaches 2 (place 0), and 5 <-> 6
    assert sorted(zip(img.tolist(), place.tolist())) == [(2, 1), (3, 0), (5, 2), (6, 1)]
    img, place = pooled_truth(image_place, image_frame, frame_place, 2, 3)
    assert sorted(zip(img.tolist(), place.tolist())) == [(1, 1), (2, 1), (3, 0), (4, 0), (4, 2), (5, 2), (6, 1),
                                                          (7, 1)]
    # places 10 frames apart: a tolerance of 2 reaches no other place
    gap = np.full(30, -1)
    gap[[0, 1, 2, 10, 11, 12, 20, 21, 22]] = np.repeat(np.arange(3), 3)
    lab = np.flatnonzero(gap >= 0)
    assert pooled_truth(gap[lab], lab, gap, 2, 3) is None
    with pytest.raises(VPRInputError, match="tolerance=-1"):
        ProtocolOptions(tolerance=-1)


def test_tolerance_counts_neighbouring_places_as_right(demo, demo_pixels):
    from vpr_explorer.protocols.scale import fast_paper_protocol

    places = make_places(demo, PlaceSpec(3, 3))
    args = (demo_pixels, places.image_place, demo.image_traversal, places.n_places)
    frames = dict(image_frame=demo.image_frame, frame_place=places.frame_place)
    exact = paper_protocol(*args, ProtocolOptions(runs=5, seed=0))
    loose = paper_protocol(*args, ProtocolOptions(runs=5, seed=0, tolerance=2), **frames)
    assert loose.settings["tolerance"] == 2 and exact.settings["tolerance"] == 0
    # more right places: a rank can only improve, and on this route it does
    for a, b in zip(exact.rows, loose.rows):
        assert b.recall[1][0] >= a.recall[1][0], a.key
    assert loose.row("place-baseline").recall[1][0] > exact.row("place-baseline").recall[1][0]
    # the fast path hands such a run to the straightforward protocol, and says so
    fast = fast_paper_protocol(*args, ProtocolOptions(runs=5, seed=0, tolerance=2), **frames)
    assert fast.same_numbers(loose) and any("frame tolerance of 2" in n for n in fast.notes)
    # where places are further apart than the tolerance, nothing changes but the setting
    apart = make_places(demo, PlaceSpec(3, 10))
    args = (demo_pixels, apart.image_place, demo.image_traversal, apart.n_places)
    frames = dict(image_frame=demo.image_frame, frame_place=apart.frame_place)
    fast = fast_paper_protocol(*args, ProtocolOptions(runs=3, tolerance=2), **frames)
    assert fast.same_numbers(paper_protocol(*args, ProtocolOptions(runs=3))) and fast.settings["tolerance"] == 2
    opened = open_set_protocol(*args, ProtocolOptions(runs=3, tolerance=2), **frames)
    assert opened.same_numbers(open_set_protocol(*args, ProtocolOptions(runs=3)))


# --------------------------------------------------------------------------- every row against plain loops


def _hard(seed=0):
    """Noisy places: neither trivial nor hopeless (asserted), so leaks and wrong rules show."""
    return _synthetic(seed=seed, n_places=10, per_place=6, dim=24, noise=2.2)


def _assert_rows_equal_loops(ev, ref, keys, with_rejection=False):
    for key in keys:
        row, want = ev.row(key), ref[key]
        for k in ev.ks:
            np.testing.assert_allclose(row.recall[k], want["recall"][k], atol=1e-12, err_msg=f"{key} R@{k}")
        np.testing.assert_allclose(row.accepted, want["accepted"], atol=1e-12, err_msg=f"{key} accepted")
        np.testing.assert_allclose(row.precision, want["precision"], atol=1e-12, err_msg=f"{key} precision")
        np.testing.assert_allclose(row.own_traversal, want["own"], atol=1e-12, err_msg=f"{key} own traversal")
        if with_rejection:
            np.testing.assert_allclose(row.unknown_rejection, want["rejection"], atol=1e-12, err_msg=f"{key} rejection")


KEYS = ("image-baseline", "place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted")


@pytest.mark.parametrize("cross_condition", [False, True])
def test_every_row_of_the_paper_protocol_equals_plain_loops(cross_condition):
    d, labels, trav = _hard()
    ev = paper_protocol(d, labels, trav, 10, ProtocolOptions(runs=6, seed=3, cross_condition=cross_condition))
    r1 = ev.row("place-baseline").recall[1][0]
    assert 0.3 < r1 < 0.95, r1  # the numbers can tell a wrong rule from a right one
    margin, raw = ev.row("margin-weighted").recall[1][0], ev.row("raw-weighted").recall[1][0]
    assert margin != raw  # the margin and raw rules differ on this data
    ref = loop_protocol(d, labels, trav, 10, draw_splits(labels, 10, runs=6, seed=3),
                        cross_condition=cross_condition)
    _assert_rows_equal_loops(ev, ref, KEYS)


def test_every_row_of_the_open_set_and_its_tradeoff_equals_plain_loops():
    d, labels, trav = _hard(seed=4)
    ks_family = (-0.5, 0.0, 2.0, 3.5)
    ev = open_set_protocol(d, labels, trav, 10, ProtocolOptions(runs=5, seed=2, unknown_share=0.3, k_grid=ks_family))
    splits = draw_splits(labels, 10, runs=5, seed=2, unknown_share=0.3)
    ref = loop_protocol(d, labels, trav, 10, splits, ks_family=ks_family)
    r1 = ev.row("place-baseline").recall[1][0]
    assert 0.3 < r1 < 0.95, r1
    _assert_rows_equal_loops(ev, ref, KEYS, with_rejection=True)
    assert ev.row("margin-weighted").unknown_rejection[0] < 1  # the numbers are not trivial either
    rejected = []
    for t in ev.tradeoff:
        if not t.series.startswith("θ_p(k)"):
            continue
        base = t.series.split()[-1]
        want = ref[("family", base, t.rule, t.param)]
        np.testing.assert_allclose(t.known_recall1, want["recall"][1], atol=1e-12, err_msg=f"{t.series} {t.rule} {t.param}")
        np.testing.assert_allclose(t.unknown_rejection, want["rejection"], atol=1e-12)
        np.testing.assert_allclose(t.precision, want["precision"], atol=1e-12)
        np.testing.assert_allclose(t.accepted, want["accepted"], atol=1e-12)
        rejected.append(t.unknown_rejection[0])
    assert len(rejected) == 16 and max(rejected) > min(rejected)  # k moves the rejection
