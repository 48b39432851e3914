"""The pass's panels on a torch device (``scale.device_panel``): on CPU tensors, or on the device
``VPR_EXPLORER_TEST_DEVICE`` names (``benchmarks/gpu_check.py`` sets it to the GPU).

``device="cpu"`` runs the device code path (the GEMM, squares, downdate products, masks,
maxima, b and the table's entries as whole-panel torch operations) on this machine. Its
results must be the numpy panels' and ``evaluation.paper_protocol``'s: the protocol's
numbers compared as ``tests/test_scale.py`` does (θ to float rounding, every outcome
exactly), and one panel's ``PanelResult`` against ``panel.panel_task``'s directly: on
descriptors whose float32 scores and sums are exact every array is equal bit for bit; on
ordinary ones V agrees to ``V_RTOL`` (float32 sums in another order) and b to ``SCORE_TOL``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import vpr_explorer.protocols.scale.blocked_pass as pass_module
from test_scale import awkward, check, structured
from vpr_explorer.protocols.evaluation import draw_splits
from vpr_explorer.protocols.options import TABLE_MEMORY, ProtocolOptions
from vpr_explorer.protocols.scale import make_layout
from vpr_explorer.protocols.scale.device_panel import DevicePanels, top2_device
from vpr_explorer.protocols.scale.full_sums import full_set_sums
from vpr_explorer.protocols.scale.layout import as_layout32
from vpr_explorer.protocols.scale.panel import BlockProducts, PassInputs, PassState, panel_task, row_floor
from vpr_explorer.protocols.scale.table import TIE, Entries, top2_rows

#: V of one panel, device against numpy: float32 sums of up to ``W_CHUNK`` columns, in another order.
V_RTOL = 1e-5
#: b and the maxima, device against numpy: torch's and numpy's float32 GEMMs may round the last bit apart.
SCORE_TOL = 1e-6


@pytest.fixture(autouse=True)
def one_torch_thread():
    """torch's CPU kernels in one thread here: the panels' tensors are small, and two OpenMP
    threads on a busy two-core machine can wait on each other far longer than they compute."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


def numpy_path_unused(monkeypatch):
    """Make the numpy panel fail if the pass calls it: the device runs must not fall back to it."""
    def refuse(*a, **k):
        raise AssertionError("the numpy panel ran on a device pass")

    monkeypatch.setattr(pass_module, "panel_task", refuse)  # read by blocked_pass


# --------------------------------------------------------------------------- the tie rule


def test_top2_on_the_device_is_top2_rows(device_under_test):
    # first slot of a repeated maximum, the second equal to the best, all −∞ rows (masked
    # places), one slot, and gaps just inside and just outside the float32 tie tolerance
    one = np.float32(0.5)
    inside, outside = one - np.float32(TIE) * np.float32(0.99), one - np.float32(TIE) * np.float32(1.01)
    rows = [
        [0.1, 0.5, 0.5, 0.2],  # best twice: t2 = t1, a2 the next slot
        [0.5, 0.1, -np.inf, 0.3],
        [-np.inf] * 4,  # a fully masked place
        [0.2, -np.inf, -np.inf, -np.inf],  # one finite slot
        [one, inside, 0.0, 0.0],  # t2 within the tolerance: near
        [one, outside, 0.0, 0.0],  # just outside: not near
        [one, 0.2, 0.2 - TIE / 2, -1.0],  # t3 ties t2: near
        [0.3, 0.3, 0.3, 0.3],
        [one, one - np.float32(TIE), 0.0, 0.0],  # exactly at the tolerance (in float32): near
    ]
    rng = np.random.default_rng(0)
    coarse = rng.integers(-3, 4, (300, 6)).astype(np.float32) / 4  # many exact ties
    coarse[rng.random(coarse.shape) < 0.2] = -np.inf
    for vals in (np.array(rows, dtype=np.float32), coarse, np.ones((0, 5), np.float32),
                 np.array([[0.4], [-np.inf]], dtype=np.float32)):
        want = top2_rows(vals)
        got = top2_device(torch.from_numpy(vals).to(device_under_test),
                          torch.tensor(np.float32(TIE), device=device_under_test))
        assert set(got) == set(want)
        for k in want:
            assert got[k].cpu().numpy().dtype == want[k].dtype, k
            np.testing.assert_array_equal(got[k].cpu().numpy(), want[k], err_msg=k)
    assert top2_rows(np.array(rows, dtype=np.float32))["near"].tolist() == [1, 0, 0, 0, 1, 0, 1, 1, 1]


# --------------------------------------------------------------------------- one panel, both ways


def exact_data(seed=0, n_places=90):
    """Descriptors in {−1, 0, 1}/4 (16 dims), places of 2..7 images, repeated images, 3 traversals.

    Their scores are multiples of 1/16 in [−1, 1], so every float32 product and every
    squared score about c = 1/16 is exact, and so is every float32 sum the pass forms (under
    2²⁴/256): both paths must give the same bits whatever their summation order.
    """
    rng = np.random.default_rng(seed)
    sizes = rng.integers(2, 8, n_places)
    labels = np.repeat(np.arange(n_places), sizes)
    d = rng.integers(-1, 2, (len(labels), 16)).astype(np.float32) / 4
    d[np.flatnonzero(labels == 3)[1]] = d[np.flatnonzero(labels == 3)[0]]  # two images of one place
    d[np.flatnonzero(labels == 50)[0]] = d[np.flatnonzero(labels == 7)[0]]  # one image in two places
    trav = rng.integers(0, 3, len(labels))
    perm = rng.permutation(len(labels))
    return d[perm], labels[perm], trav[perm]


def panel_states(d, labels, trav, n_places, block, panel_rows, *, cross_condition, centre=None, device="cpu"):
    """Numpy and device ``PassState`` of these images, with every row's floor (from a numpy pass)."""
    lay = make_layout(labels, n_places, block)
    splits = draw_splits(labels, n_places, runs=3, seed=1)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    x = as_layout32(d, lay)
    if centre is None:
        centre = full_set_sums(d, lay, query_rows).centre
    row_trav = None
    if cross_condition:
        row_trav = np.full(lay.n_rows, -1, dtype=np.int64)
        real = lay.image_of_row >= 0
        row_trav[real] = trav[lay.image_of_row[real]]
    inputs = PassInputs(x, lay, query_rows, row_trav, (0.0, 0.3), centre)
    pas = pass_module.blocked_pass(inputs, Entries(lay, TABLE_MEMORY, None), 7, ProtocolOptions(threads=1),
                                   panel_rows=panel_rows)
    st_np = PassState(inputs, BlockProducts(x, None), panel_rows)
    st_dev = PassState(inputs, BlockProducts(x, torch.device(device)), panel_rows)
    for st in (st_np, st_dev):
        st.floor[:] = row_floor(pas.best_own, inputs.mu_range, st.is_query)
    panels = []
    for bi in range(lay.n_blocks):
        panels += pass_module.panels_of(lay, bi, bi, max(1, panel_rows // pass_module.DIAGONAL_SPLIT))
        for bj in range(bi + 1, lay.n_blocks):
            panels += pass_module.panels_of(lay, bi, bj, panel_rows)
    return st_np, st_dev, panels


def compare_panels(a, b, *, exact):
    """Two ``PanelResult``s of one panel: equal, V and b to tolerance unless ``exact``."""
    assert a.panel == b.panel
    np.testing.assert_array_equal(b.rows, a.rows)
    if isinstance(a.cols, slice):
        assert b.cols == a.cols
    else:
        np.testing.assert_array_equal(b.cols, a.cols)
    assert (a.v_cols is None) == (b.v_cols is None) and (a.best is None) == (b.best is None)
    pairs = [(a.v_rows, b.v_rows)] + ([(a.v_cols, b.v_cols)] if a.v_cols is not None else [])
    for x, y in pairs:
        assert y.dtype == x.dtype == np.float64 and y.shape == x.shape
        if exact:
            np.testing.assert_array_equal(y, x)
        else:
            np.testing.assert_allclose(y, x, rtol=V_RTOL, atol=0)
    if a.best is not None:
        assert b.best.dtype == a.best.dtype == np.float32
        if exact:
            np.testing.assert_array_equal(b.best, a.best)
        else:
            np.testing.assert_allclose(b.best, a.best, rtol=0, atol=SCORE_TOL)
    if not exact:
        return
    assert [blk for blk, _ in a.sides] == [blk for blk, _ in b.sides]
    for (_, x), (_, y) in zip(a.sides, b.sides):
        assert set(x) == set(y)
        for k in x:
            if x[k] is None:
                assert y[k] is None, k
                continue
            assert y[k].dtype == x[k].dtype and y[k].shape == x[k].shape, k
            np.testing.assert_array_equal(y[k], x[k], err_msg=k)


@pytest.mark.parametrize("cross_condition", [False, True])
@pytest.mark.parametrize("block,panel_rows", [(140, 1), (140, 30), (300, 10**6)])
def test_a_panel_on_the_device_equals_the_numpy_panel_bit_for_bit(cross_condition, block, panel_rows,
                                                                   device_under_test):
    # exact scores and sums (exact_data): V, b and both sides of the table, every entry with
    # its slots, near flags and own-place marks, equal; panels of one place, of several, and
    # of a whole block; diagonal ones wait for nothing here (every floor is set)
    d, labels, trav = exact_data()
    st_np, st_dev, panels = panel_states(d, labels, trav, 90, block, panel_rows, cross_condition=cross_condition,
                                         centre=1 / 16, device=device_under_test)
    dev = DevicePanels(st_dev)
    n_entries = n_near = 0
    for p in panels:
        a, b = panel_task(st_np, p), dev.task(p)
        compare_panels(a, b, exact=True)
        n_entries += sum(len(s["row"]) for _, s in a.sides)
        n_near += sum(int(s["near"].sum()) for _, s in a.sides)
    assert len(panels) > 3 and n_entries > 1000 and n_near > 100  # the tie rule and the selection get exercised
    if panel_rows == 1:
        assert all(p.g1 - p.g0 == 1 for p in panels)


def test_a_panel_on_the_device_with_ordinary_scores(device_under_test):
    # unit descriptors: torch's and numpy's GEMMs may round apart, V's float32 sums run in
    # another order; V to V_RTOL, b to SCORE_TOL (the protocol tests below check the outcomes)
    d, labels, trav = awkward(seed=3)
    st_np, st_dev, panels = panel_states(d, labels, trav, 260, 500, 200, cross_condition=True,
                                         device=device_under_test)
    dev = DevicePanels(st_dev)
    for p in panels:
        compare_panels(panel_task(st_np, p), dev.task(p), exact=False)


# --------------------------------------------------------------------------- the protocol


@pytest.mark.parametrize("panel_rows,threads,cross_condition", [(1, 1, False), (45, 2, True), (10**6, 2, False)])
def test_device_pass_equals_paper_protocol_unequal_places(monkeypatch, panel_rows, threads, cross_condition,
                                                          device_under_test):
    # padding (places of 2..15 images), empty place ids, duplicates within and across places,
    # a place seen in one traversal; panels of one place, of a few, and spanning the block
    numpy_path_unused(monkeypatch)
    monkeypatch.setattr(pass_module, "DEVICE_PANEL_ROWS", panel_rows)  # read by blocked_pass
    d, labels, trav = awkward(seed=2)
    check(monkeypatch, d, labels, trav, 260, seed=1, runs=2, cross_condition=cross_condition, user_theta=0.2,
          ks=(1, 2, 7), fast_kw={"block": 500, "threads": threads, "device": device_under_test})


def test_device_pass_equals_paper_protocol_structured_and_hard(monkeypatch, device_under_test):
    # neighbouring places correlated (many near ties at the top), then heavy noise (many
    # wrong places above the own one; image-level records beyond K)
    numpy_path_unused(monkeypatch)
    d, labels, trav = structured(seed=3, n_places=200, per_place=8, dim=64)
    check(monkeypatch, d, labels, trav, 200, runs=3, user_theta=0.3, fast_kw={"block": 700, "device": device_under_test})
    d, labels, trav = awkward(seed=1, noise=4.0)
    check(monkeypatch, d, labels, trav, 260, runs=2, ks=(1, 3), fast_kw={"block": 600, "device": device_under_test, "threads": 1})


def test_device_pass_does_not_depend_on_threads(device_under_test):
    # panels merge in task order: 1 and 2 threads give the same sums, b and table, bit for bit
    d, labels, _ = awkward(seed=4)
    lay = make_layout(labels, 260, 400)
    splits = draw_splits(labels, 260, runs=3, seed=2)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    inputs = PassInputs(as_layout32(d, lay), lay, query_rows, None, (0.0, 0.2),
                        full_set_sums(d, lay, query_rows).centre)
    out = []
    for threads in (1, 2):
        entries = Entries(lay, TABLE_MEMORY, None)
        pas = pass_module.blocked_pass(inputs, entries, 7, ProtocolOptions(threads=threads, device=device_under_test),
                                       panel_rows=60)
        out.append((pas, [entries.get(b) for b in range(lay.n_blocks)]))
    (p1, t1), (p2, t2) = out
    np.testing.assert_array_equal(p2.v, p1.v)
    np.testing.assert_array_equal(p2.best_own, p1.best_own)
    np.testing.assert_array_equal(p2.records.n, p1.records.n)
    np.testing.assert_array_equal(p2.records.place, p1.records.place)
    for a, b in zip(t1, t2):
        for k in a:
            np.testing.assert_array_equal(b[k], a[k], err_msg=k)
    assert sum(len(t["row"]) for t in t1) > 1000


@pytest.mark.realdata
def test_device_pass_nordland_pixels_equals_paper_protocol(monkeypatch, data_root, device_under_test):
    # Nordland g3s3 pixels, its first 300 places (1,800 images × 2,048): tunnels of
    # byte-identical frames tie at the top
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.method.places import PlaceSpec, make_places
    from vpr_explorer.pipeline import dataset_descriptors

    numpy_path_unused(monkeypatch)
    dataset = load_dataset(data_root / "Nordland_64x32")
    places = make_places(dataset, PlaceSpec(3, 3))
    keep = (places.image_place >= 0) & (places.image_place < 300)
    desc = np.asarray(dataset_descriptors(dataset, "pixels"))[keep]
    labels, trav = places.image_place[keep], np.asarray(dataset.image_traversal)[keep]
    assert desc.shape == (1800, 2048)
    check(monkeypatch, desc, labels, trav, 300, runs=2, fast_kw={"block": 1000, "device": device_under_test})
