"""Precision–recall through the protocols, the report, the figure and the command line."""
import json

import numpy as np

from reference import synthetic_places, unit_rows
from vpr_explorer.protocols import scale
from vpr_explorer.protocols.scale import protocol as scale_protocol
from vpr_explorer.cli import main
from vpr_explorer.protocols.evaluation import open_set_protocol, paper_protocol, retrieval_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.pipeline import run_protocol
from vpr_explorer.views.plots import evaluation_pr_figure
from vpr_explorer.protocols.precision_recall import GLOBAL_CURVE
from vpr_explorer.views.report import render


def _synthetic(seed=0, n_places=12, per_place=6, dim=32, noise=0.9, n_trav=3):
    d, labels, trav = synthetic_places(seed, n_places, per_place, dim, noise, n_trav)
    return d.astype(np.float32), labels, trav


def assert_same_pr(a: dict, b: dict, where: str = "") -> None:
    """Equal PR rows, thresholds within 1e-6. A threshold can be a score (the oracle θ: a
    query's top score), and the blocked pass scores with other GEMMs than the reference: the
    same float32 number on OpenBLAS's SkylakeX kernel, a few ulp apart on its Haswell kernel.
    Counts, precision and recall must be equal (the tie tolerance absorbs those ulp)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            if k in ("threshold", "max_f1_threshold"):
                np.testing.assert_allclose(np.asarray(a[k], dtype=float), np.asarray(b[k], dtype=float), rtol=0,
                                           atol=1e-6, err_msg=f"{where}.{k}")
            else:
                assert_same_pr(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_pr(x, y, f"{where}[{i}]")
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"


def test_paper_and_fast_paper_agree(monkeypatch):
    d, lab, trav = _synthetic()
    options = ProtocolOptions(runs=4, pr=True, user_theta=0.3)
    ev = paper_protocol(d, lab, trav, 12, options)
    assert len(ev.pr) == len(ev.rows)
    fast = scale.fast_paper_protocol(d, lab, trav, 12, options)
    assert [r.to_dict() for r in fast.pr] == [r.to_dict() for r in ev.pr]
    monkeypatch.setattr(scale_protocol, "PR_FAMILY_CELLS", 0)  # read by fast_paper_protocol
    blocked = scale.fast_paper_protocol(d, lab, trav, 12, options)
    globals_ = {"image-baseline", "place-baseline", "global-auto", "global-oracle", "global-user"}
    assert {r.key for r in blocked.pr} == globals_  # the blocked pass keeps no raw_p: no family curves
    by = {r.key: r for r in ev.pr}
    for r in blocked.pr:
        assert_same_pr(r.to_dict(), by[r.key].to_dict(), r.key)
    assert any("left out" in n for n in blocked.notes)
    json.dumps(ev.to_dict(), allow_nan=False)
    text = render(ev)
    assert "precision–recall" in text and "R@100P" in text
    fig = evaluation_pr_figure(ev)
    assert {t.meta for t in fig.data} >= {GLOBAL_CURVE, "own raw, weighted θ"}
    fig.to_json()
    # no pr: unchanged
    plain = paper_protocol(d, lab, trav, 12, ProtocolOptions(runs=4, user_theta=0.3))
    assert plain.pr == () and "pr" not in plain.to_dict() and plain.same_numbers(ev)


def test_open_set_and_traversal(demo, demo_pixels):
    d, lab, trav = _synthetic(1)
    ev = open_set_protocol(d, lab, trav, 12, ProtocolOptions(runs=3, pr=True))
    assert all(r.n_unknown > 0 for r in ev.pr)
    # the demo route: day and night against snow, places of 2 frames
    tv = run_protocol("traversal", demo, make_places(demo, PlaceSpec(2, 2)), demo_pixels,
                      ProtocolOptions(database=("day", "night"), queries="snow", pr=True))
    assert [r.key for r in tv.pr] == [r.key for r in tv.rows]


def test_retrieval_protocol(monkeypatch):
    rng = np.random.default_rng(2)
    db = unit_rows(rng, 40, 16).astype(np.float32)
    place = np.repeat(np.arange(10), 4)
    place[-2:] = -1
    q_idx = rng.integers(0, 40, 25)
    q = db[q_idx] + 0.3 * rng.normal(size=(25, 16)).astype(np.float32) / 4
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    lists = [[int(i)] if k % 5 else [] for k, i in enumerate(q_idx)]
    gt = GroundTruth.from_lists(lists, 40, "test")
    ev = retrieval_protocol(db, q, place, 10, gt, ProtocolOptions(pr=True), block=7)
    keys = [r.key for r in ev.pr]
    assert keys[0] == "image-baseline" and "margin-weighted" in keys
    img = ev.pr[0]
    assert img.n_known + img.n_unknown == 25
    import vpr_explorer.protocols.evaluation as evm
    monkeypatch.setattr(evm, "PR_RAW_CELLS", 0)
    ev2 = evm.retrieval_protocol(db, q, place, 10, gt, ProtocolOptions(pr=True), block=7)
    assert "margin-weighted" not in [r.key for r in ev2.pr] and any("left out" in n for n in ev2.notes)
    b = {r.key: r for r in ev.pr}
    for r in ev2.pr:
        assert r.to_dict() == b[r.key].to_dict()


def test_cli_pr(tmp_path, capsys):
    out = tmp_path / "e.json"
    code = main(["evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
                 "--runs", "3", "--pr", "--json", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    data = json.loads(out.read_text())
    assert data["pr"] and GLOBAL_CURVE in data["pr_curves"]
    code = main(["evaluate", "--dataset", "demo", "--descriptor", "pixels", "--group", "2", "--step", "4",
                 "--protocol", "open-set", "--runs", "3", "--pr"])
    text = capsys.readouterr().out
    assert code == 0
