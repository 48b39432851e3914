"""The full-set sums on a torch device (``scale.full_sums.device_set_sums``) against numpy's ``full_set_sums``.

``device_under_test`` is "cpu" here (the device code on CPU tensors) and the GPU on a machine
with one. Both paths form the same float64 sums in another order, so they agree to float64
rounding: every element within ``SUMS_RTOL`` of its sum's magnitude (the sum of its terms'
absolute values, from a plain float64 reference), with c equal; on descriptors whose sums are
exact in float64 they agree bit for bit. The protocol with the device gives the numbers of
the numpy run and of ``evaluation.paper_protocol``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import vpr_explorer.protocols.scale.full_sums as full_sums
from test_scale import awkward, check, structured
from test_scale_device import exact_data, one_torch_thread  # noqa: F401 (an autouse fixture)
from vpr_explorer.protocols.evaluation import draw_splits
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.scale import fast_paper_protocol, make_layout
from vpr_explorer.protocols.scale.full_sums import device_set_sums, full_set_sums
from vpr_explorer.protocols.scale.layout import as_layout32

#: Device against numpy, each element relative to its sum's magnitude: float64 sums of up to
#: N + D terms in another order differ by at most about (N + D)·2⁻⁵³ of it (3·10⁻¹³ at
#: N = 3,000); observed up to 7e-16 on the synthetic cases here and 8.4e-15 on Nordland
#: pixels (within-place grams of 2,048 terms; under 1e-15 for the other sums).
SUMS_RTOL = 1e-12
FIELDS = ("dot_other", "dot_queries", "gram", "a_centred")


def layout_case(d, labels, n_places, block, runs=4, seed=3):
    lay = make_layout(labels, n_places, block)
    splits = draw_splits(labels, n_places, runs=runs, seed=seed)
    return lay, np.stack([lay.row_of_image[sp.queries] for sp in splits])


def layout_rows64(d, lay):
    """``(n_rows, D)`` the descriptors' own values in float64, zero rows for padding."""
    real = lay.image_of_row >= 0
    x = np.zeros((lay.n_rows, d.shape[1]))
    x[real] = d[lay.image_of_row[real]].astype(np.float64)
    return x


def plain_sums(d, lay, query_rows):
    """Every field of ``FullSums`` from its definition over the score matrix S = X Xᵀ (float64),
    and each element's magnitude: the sum of the absolute values of the terms it adds."""
    x = layout_rows64(d, lay)
    real = lay.image_of_row >= 0
    s, t = x @ x.T, np.abs(x) @ np.abs(x).T  # t: Σ_k |x_ik||x_jk|, each score's terms
    same = lay.place_of_row[:, None] == lay.place_of_row[None, :]
    other = ~same & real[None, :]  # j ∉ p(i), padding left out
    n = int(real.sum())
    centre = float(np.float32((s.sum() - np.trace(s)) / (n * (n - 1))))
    p, m = len(lay.places), lay.slots
    rows_pm = lay.row_of(np.repeat(np.arange(p), m), np.tile(np.arange(m), p)).reshape(p, m)
    place_pairs = (rows_pm[:, :, None], rows_pm[:, None, :])
    dot_other = np.where(other, s, 0.0).sum(axis=1)
    value = {
        "dot_other": dot_other,
        "dot_queries": x @ x[query_rows].sum(axis=1).T,
        "gram": s[place_pairs],
        "a_centred": np.where(real, np.where(other, (s - centre) ** 2, 0.0).sum(axis=1), 0.0),
    }
    # dᵢ·T and dᵢ·T_p are both sums over all rows; aᵢ comes from dᵢᵀCdᵢ (Σⱼ sᵢⱼ² term by
    # term), 2c·dᵢ·(T − T_p) and c²·n_other
    size = {
        "dot_other": t.sum(axis=1),
        "dot_queries": np.abs(x) @ np.abs(x[query_rows]).sum(axis=1).T,
        "gram": t[place_pairs],
        "a_centred": np.where(real, (t**2).sum(axis=1) + 2 * abs(centre) * t.sum(axis=1) + centre**2 * n, 0.0),
    }
    return value, size, centre


def worst_ratio(a, b, size):
    """max |a − b| / size over the elements (0/0 counts 0; a difference where size is 0, inf)."""
    diff = np.abs(a - b)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(diff == 0, 0.0, diff / size)
    return float(ratio.max()) if ratio.size else 0.0


def assert_close_sums(got, want, size):
    """``got`` against ``want``: same types, dtypes and shapes, c equal, each element within
    ``SUMS_RTOL`` of its magnitude; returns the worst ratio seen."""
    assert type(got) is type(want)
    assert got.centre == want.centre and isinstance(got.centre, float)
    worst = 0.0
    for field in FIELDS:
        a, b = getattr(got, field), getattr(want, field)
        assert isinstance(a, np.ndarray) and a.dtype == b.dtype == np.float64 and a.shape == b.shape, field
        ratio = worst_ratio(a, b, size[field])
        assert ratio <= SUMS_RTOL, (field, ratio)
        worst = max(worst, ratio)
    return worst


# --------------------------------------------------------------------------- the sums


@pytest.mark.parametrize("block", [40, 140, 10**5])
def test_device_sums_equal_numpy_bit_for_bit_on_exact_values(device_under_test, block):
    # descriptors in {−1, 0, 1}/4 (16 dims), places of 2..7 images: every product and sum is
    # exact in float64, so both paths give the same bits, whatever their order; blocks of a
    # few places (the last shorter), several, and one block
    d, labels, _ = exact_data(seed=1)
    lay, query_rows = layout_case(d, labels, 90, block, runs=3)
    want = full_set_sums(d, lay, query_rows, 2)
    for x32 in (None, as_layout32(d, lay)):
        got = device_set_sums(d, lay, query_rows, device_under_test, x32)
        assert got.centre == want.centre
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    value, size, centre = plain_sums(d, lay, query_rows)
    assert got.centre == centre
    for field in ("dot_other", "dot_queries", "gram"):  # against the definition, exactly
        np.testing.assert_array_equal(getattr(got, field), value[field], err_msg=field)
    # c = 0.0625… is not a short binary fraction: (s − c)² summed term by term rounds otherwise
    assert worst_ratio(got.a_centred, value["a_centred"], size["a_centred"]) <= SUMS_RTOL
    assert lay.sizes.min() < lay.slots  # padding slots: their rows and grams are zero
    assert not got.a_centred[lay.image_of_row < 0].any() and not got.dot_queries[lay.image_of_row < 0].any()


def test_device_sums_hand_computed(device_under_test):
    # places 0 (images a, b) and 1 (image c, then a padding slot); split 0 queries a and c:
    # a = (1, 0), b = (0, 1), c = (1, 1)/2 → a·b = 0, a·c = b·c = 1/2; c = mean over the 6
    # ordered pairs of distinct images = (0 + 1/2 + 1/2)·2/6 = 1/3
    d = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
    labels = np.array([0, 0, 1])
    lay = make_layout(labels, 2, 100)
    query_rows = lay.row_of_image[[[0, 2]]]
    got = device_set_sums(d, lay, query_rows, device_under_test)
    assert got.centre == float(np.float32(1 / 3))
    c = got.centre
    row = lay.row_of_image
    np.testing.assert_array_equal(got.dot_other[row], [0.5, 0.5, 1.0])
    np.testing.assert_array_equal(got.dot_queries[row, 0], [1.5, 0.5, 1.0])  # dᵢ·(a + c)
    np.testing.assert_array_equal(got.gram[0], [[1.0, 0.0], [0.0, 1.0]])
    np.testing.assert_array_equal(got.gram[1], [[0.5, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(got.a_centred[row], [(0.5 - c) ** 2, (0.5 - c) ** 2, 2 * (0.5 - c) ** 2], rtol=1e-15)
    assert got.a_centred[lay.image_of_row < 0].tolist() == [0.0]


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_device_sums_match_numpy_to_float64_rounding(device_under_test, dtype):
    # unit descriptors (float64 ones off the float32 grid), places of 2..15 images (padding),
    # empty place ids and skipped frames; blocks of a few places, several, and one; from the
    # protocol's float32 layout rows or gathered from the descriptors
    d, labels, _ = awkward(seed=5)
    if dtype == np.float64:
        d = d.astype(np.float64) + 1e-6 * np.random.default_rng(0).standard_normal(d.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d.astype(dtype)
    for block in (60, 250, 10**5):
        lay, query_rows = layout_case(d, labels, 260, block)
        assert lay.sizes.min() < lay.slots
        value, size, _ = plain_sums(d, lay, query_rows)
        want = full_set_sums(d, lay, query_rows, 2, as_layout32(d, lay))
        for x32 in (None, as_layout32(d, lay)):
            got = device_set_sums(d, lay, query_rows, device_under_test, x32)
            assert_close_sums(got, want, size)
            for field in FIELDS:  # and both against the definition
                assert worst_ratio(getattr(got, field), value[field], size[field]) <= SUMS_RTOL, field


def test_float64_descriptors_are_not_rounded_to_float32(device_under_test):
    # the protocol hands the float32 layout rows to the sums whatever the dtype: float64
    # descriptors must be summed from their own values (a float32 rounding moves the sums
    # by ~1e-9 of their magnitude, hundreds of times the tolerance)
    d, labels, _ = awkward(seed=6)
    d = d.astype(np.float64) + 1e-4 * np.random.default_rng(1).standard_normal(d.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lay, query_rows = layout_case(d, labels, 260, 500)
    _, size, _ = plain_sums(d, lay, query_rows)
    got = device_set_sums(d, lay, query_rows, device_under_test, as_layout32(d, lay))
    assert_close_sums(got, full_set_sums(d, lay, query_rows, 1), size)
    rounded = full_set_sums(d.astype(np.float32), lay, query_rows, 1)
    assert worst_ratio(got.dot_other, rounded.dot_other, size["dot_other"]) > 100 * SUMS_RTOL


def test_full_set_sums_hands_a_device_to_device_set_sums(monkeypatch):
    d, labels, _ = exact_data(seed=2)
    lay, query_rows = layout_case(d, labels, 90, 200)
    calls = []
    real = full_sums.device_set_sums

    def counted(*a):
        calls.append(a[3])
        return real(*a)

    monkeypatch.setattr(full_sums, "device_set_sums", counted)  # read by full_set_sums
    full_set_sums(d, lay, query_rows, 2, as_layout32(d, lay))
    assert calls == []
    sums = full_set_sums(d, lay, query_rows, 2, as_layout32(d, lay), ProtocolOptions(device="cpu").device)
    assert [str(c) for c in calls] == ["cpu"] and isinstance(sums, full_sums.FullSums)


# --------------------------------------------------------------------------- the protocol


def numpy_sums_unused(monkeypatch):
    """Make the numpy sums' lanes fail if anything runs them: a device run must not."""
    def refuse(*a, **k):
        raise AssertionError("the numpy full-set sums ran on a device run")

    monkeypatch.setattr(full_sums, "run_in_lanes", refuse)  # read by full_set_sums


@pytest.mark.parametrize("case", ["awkward", "structured"])
def test_device_run_equals_numpy_run_and_paper_protocol(monkeypatch, device_under_test, case):
    # the whole protocol with the sums (and the pass) on the device: the numbers of the numpy
    # run and of paper_protocol (outcomes exactly, θ to THETA_TOL), for unequal places with
    # duplicates in cross-condition, and for correlated neighbouring places (near ties)
    if case == "awkward":
        d, labels, trav = awkward(seed=2)
        n_places, kw, fast_kw = 260, {"cross_condition": True, "user_theta": 0.2, "ks": (1, 2, 7)}, {"block": 500}
    else:
        d, labels, trav = structured(seed=3, n_places=150, per_place=8, dim=64)
        n_places, kw, fast_kw = 150, {"user_theta": 0.3}, {"block": 400, "threads": 1}
    options = ProtocolOptions(runs=2, **kw)
    numpy_run = fast_paper_protocol(d, labels, trav, n_places, dataclasses.replace(options, **fast_kw))
    numpy_sums_unused(monkeypatch)
    calls = []
    real = full_sums.device_set_sums
    monkeypatch.setattr(full_sums, "device_set_sums", lambda *a: calls.append(a[3]) or real(*a))
    ref, device_run = check(monkeypatch, d, labels, trav, n_places, runs=2, **kw,
                            fast_kw={**fast_kw, "device": device_under_test})
    assert device_run.same_numbers(numpy_run) and device_run.same_numbers(ref)
    assert len(calls) == 2  # fast_paper_protocol's and scale_splits' sums, on the device


@pytest.mark.realdata
def test_device_sums_nordland_pixels(data_root, device_under_test):
    # Nordland g3s3 pixels, its first 300 places (1,800 images × 2,048, scores near 0.9:
    # sums of large terms that cancel little), and tunnels of byte-identical frames
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.method.places import PlaceSpec, make_places
    from vpr_explorer.pipeline import dataset_descriptors

    dataset = load_dataset(data_root / "Nordland_64x32")
    places = make_places(dataset, PlaceSpec(3, 3))
    keep = (places.image_place >= 0) & (places.image_place < 300)
    d = np.asarray(dataset_descriptors(dataset, "pixels"))[keep]
    labels = places.image_place[keep]
    assert d.shape == (1800, 2048)
    lay, query_rows = layout_case(d, labels, 300, 1000, runs=5)
    _, size, _ = plain_sums(d, lay, query_rows)
    want = full_set_sums(d, lay, query_rows, 2, as_layout32(d, lay))
    assert_close_sums(device_set_sums(d, lay, query_rows, device_under_test, as_layout32(d, lay)), want, size)
