"""Nothing in a dataset folder is run: a VPR-Bench ground truth is read without unpickling code.

A ``ground_truth_new.npy`` whose pickle would create a marker file (a ``__reduce__``
calling ``open(marker, "w")``), and a bare pickle renamed ``ground_truth_new.npy``, are
refused by the library (``VPRInputError`` naming the file), by the real command line in a
subprocess (exit 2, one ``error:`` line) and by the app under AppTest (an ``st.error``, no
exception); the marker never appears. What VPR-Bench writes still loads, with the right
positives: its object array of ``[query index, [reference indices]]`` rows (from today's
numpy, and a file its Python 2 numpy wrote), an object array of per-query index arrays and
a 2-D integer array. Every other odd file (0-d, a dict, truncated, float, complex or NaN
indices) is refused with one message naming it; no index is ever rounded. A scan of the
package's source keeps pickles out of every other reader.
"""

from __future__ import annotations

import ast
import base64
import builtins
import collections
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

import vpr_explorer
from cli_run import assert_one_error_line
from images import write_random_png
# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import fresh_caches, navigation_mode  # noqa: F401
from vpr_explorer.app import ENTRY
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.layouts import VPR_BENCH_GT, Layout
from vpr_explorer.pipeline import open_dataset
from vpr_explorer.data.safe_npy import as_indices, read_npy

N_REF, N_QUERY = 10, 10
TIMEOUT = 60

# datasets/oneimage/ground_truth_new.npy of VPR-Bench (github.com/MubarizZaffar/VPR-Bench, MIT
# licence), as its Python 2 numpy pickled it: globals under numpy.core.multiarray, str dtype codes.
VPR_BENCH_PY2 = base64.b64decode(
    "k05VTVBZAQB2AHsnZGVzY3InOiAnfE8nLCAnZm9ydHJhbl9vcmRlcic6IEZhbHNlLCAnc2hhcGUnOiAoMTAsIDIpLCB9ICAgICAgICAg"
    "ICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgICAgIAqAAmNudW1weS5jb3JlLm11bHRpYXJyYXkKX3Jl"
    "Y29uc3RydWN0CnEBY251bXB5Cm5kYXJyYXkKcQJLAIVVAWKHUnEDKEsBSwpLAoZjbnVtcHkKZHR5cGUKcQRVAk84SwBLAYdScQUoSwNV"
    "AXxOTk5K/////0r/////Sz90YoldcQYoSwBdcQcoSwBLAUsCZUsBXXEIKEsASwFLAksDZUsCXXEJKEsASwFLAksDSwRlSwNdcQooSwFL"
    "AksDSwRLBWVLBF1xCyhLAksDSwRLBUsGZUsFXXEMKEsDSwRLBUsGSwdlSwZdcQ0oSwRLBUsGSwdLCGVLB11xDihLBUsGSwdLCEsJZUsI"
    "XXEPKEsGSwdLCEsJZUsJXXEQKEsHSwhLCWVldGIu"
)
VPR_BENCH_PY2_ROWS = {q: list(range(max(0, q - 2), min(N_REF, q + 3))) for q in range(N_QUERY)}


class MarkerPayload:
    """Unpickled by ``pickle``, this opens ``marker`` for writing: the file appears (and nothing else happens)."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


def vpr_bench_folder(root: Path) -> Path:
    """``ref/`` and ``query/`` of small random PNGs (``0.png`` ...), without a ground truth yet."""
    for side, n, seed in (("ref", N_REF, 0), ("query", N_QUERY, 100)):
        (root / side).mkdir(parents=True)
        for i in range(n):
            write_random_png(root / side / f"{i}.png", seed=seed + i, size=(16, 12))
    return root


def object_rows(rows) -> np.ndarray:
    """VPR-Bench's ground truth: an ``(n, 2)`` object array of ``[query index, [reference indices]]``."""
    gt = np.empty((len(rows), 2), dtype=object)
    for i, (q, refs) in enumerate(rows):
        gt[i, 0], gt[i, 1] = q, refs
    return gt


def per_query(arrays) -> np.ndarray:
    out = np.empty(len(arrays), dtype=object)
    for i, a in enumerate(arrays):
        out[i] = a
    return out


def positives(root: Path) -> dict[int, list[int]]:
    ds = open_dataset(root)
    assert ds.layout is Layout.VPR_BENCH
    return {q: ds.ground_truth.positives(q).tolist() for q in range(ds.ground_truth.n_queries)}


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The command line in a subprocess, importing the same ``vpr_explorer`` as the tests."""
    path = os.pathsep.join([str(Path(vpr_explorer.__file__).parent.parent), os.environ.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "vpr_explorer.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": path})



# --------------------------------------------------------------------------- code in the file


def write_reduce_payload(gt: Path, marker: Path) -> None:
    """Written as ``np.save`` writes any object array: the payload is one row's references."""
    np.save(gt, object_rows([(0, [0]), (1, MarkerPayload(marker))]), allow_pickle=True)


def write_bare_pickle(gt: Path, marker: Path) -> None:
    gt.write_bytes(pickle.dumps([[0, [0]], MarkerPayload(marker)]))


PAYLOADS = {"reduce-in-object-array": (write_reduce_payload, "refused: its pickled data asks for io.open"),
            "bare-pickle": (write_bare_pickle, "not a NumPy .npy file")}


@pytest.fixture(params=sorted(PAYLOADS))
def booby_trapped(request, tmp_path) -> tuple[Path, Path, str]:
    """(dataset folder, marker that must never appear, what the refusal says)."""
    write, says = PAYLOADS[request.param]
    root = vpr_bench_folder(tmp_path / "downloaded")
    marker = tmp_path / "MARKER"
    write(root / VPR_BENCH_GT, marker)
    return root, marker, says


def assert_not_run(marker: Path) -> None:
    assert not marker.exists(), f"the file's pickle ran: it created {marker}"


def test_the_library_refuses_a_ground_truth_that_would_run_code(booby_trapped):
    root, marker, says = booby_trapped
    with pytest.raises(VPRInputError) as info:
        open_dataset(root)
    assert_not_run(marker)
    text = str(info.value)
    assert text.startswith(f"{root / VPR_BENCH_GT}: ") and says in text and "\n" not in text, text
    assert "nothing in the file was run" in text
    with pytest.raises(VPRInputError, match=says):
        read_npy(root / VPR_BENCH_GT)
    assert_not_run(marker)


def test_the_command_line_refuses_it_in_one_line(booby_trapped):
    root, marker, says = booby_trapped
    result = run_cli("list", "--dataset", str(root), cwd=root.parent)
    assert_not_run(marker)
    assert_one_error_line(result, str(root / VPR_BENCH_GT), says)


def test_the_app_refuses_it_with_an_error_and_no_traceback(booby_trapped, monkeypatch):
    root, marker, says = booby_trapped
    monkeypatch.setenv("VPR_EXPLORER_DATA_ROOT", str(root.parent))
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source=str(root))
    at.run()
    assert_not_run(marker)
    assert not at.exception, [e.value for e in at.exception]
    assert any(VPR_BENCH_GT in e.value and says in e.value for e in at.error), [e.value for e in at.error]


class Reduces:
    """Pickled as ``function(*args)`` (and ``BUILD`` with ``state``): a hand-made numpy pickle."""

    def __init__(self, *reduced) -> None:
        self.reduced = reduced

    def __reduce__(self):
        return self.reduced


HUGE = Reduces(np.empty(0).__reduce__()[0], (np.ndarray, (0,), b"b"), (1, (10**12,), np.dtype(np.int64), False, b""))
ONLY_NUMPYS_PLAIN_ARRAYS = {
    "another class": (collections.OrderedDict(a=1), "asks for collections.OrderedDict"),
    "a record array": (np.zeros(2, dtype=[("a", "<i8")]), "asks for numpy.dtype('V8')"),
    "a direct ndarray call": (Reduces(np.ndarray, ((2,), "i8")), "asks for a direct call of numpy.ndarray"),
    "a huge claimed shape": (HUGE, "asks for an array of shape (1000000000000,) int64 with 0 bytes of data"),
}


@pytest.mark.parametrize("case", sorted(ONLY_NUMPYS_PLAIN_ARRAYS))
def test_only_numpys_plain_arrays_are_rebuilt(tmp_path, case):
    # harmless in themselves, but nothing but numpy's arrays of numbers is ever built from a file
    item, says = ONLY_NUMPYS_PLAIN_ARRAYS[case]
    gt = tmp_path / VPR_BENCH_GT
    np.save(gt, object_rows([(0, item)]), allow_pickle=True)
    with pytest.raises(VPRInputError, match=f"{re.escape(str(gt))}: refused: its pickled data {re.escape(says)}"):
        read_npy(gt)


# --------------------------------------------------------------------------- what VPR-Bench writes


def test_vpr_benchs_object_array_loads_with_its_positives(tmp_path):
    root = vpr_bench_folder(tmp_path / "vb")
    # as VPR-Bench's scripts fill it: lists (Python 2's range), numpy arrays, numpy integers, a tuple
    rows = [(0, [0, 1]), (np.int64(1), np.array([1, 2, 3])), (2, (2,)), (4, np.arange(3, 6, dtype=np.int32)),
            (3, []), (9, [9])]
    np.save(root / VPR_BENCH_GT, object_rows(rows), allow_pickle=True)
    got = positives(root)
    assert got == {0: [0, 1], 1: [1, 2, 3], 2: [2], 3: [], 4: [3, 4, 5], 5: [], 6: [], 7: [], 8: [], 9: [9]}


def test_a_ground_truth_written_by_vpr_benchs_python_2_numpy_loads(tmp_path):
    root = vpr_bench_folder(tmp_path / "vb")
    (root / VPR_BENCH_GT).write_bytes(VPR_BENCH_PY2)
    assert positives(root) == VPR_BENCH_PY2_ROWS


def test_per_query_index_arrays_and_a_2d_integer_array_load(tmp_path):
    root = vpr_bench_folder(tmp_path / "vb")
    want = {q: sorted({q, min(q + 1, N_REF - 1)}) for q in range(N_QUERY)}
    want[3] = []
    np.save(root / VPR_BENCH_GT, per_query([np.array(want[q], dtype=np.int64) for q in range(N_QUERY)]),
            allow_pickle=True)
    assert positives(root) == want

    # equal-length rows make numpy write a plain integer array: row i lists query i's references
    table = np.array([[q, (q + 5) % N_REF] for q in range(N_QUERY)], dtype=np.uint16)
    np.save(root / VPR_BENCH_GT, table, allow_pickle=False)
    assert positives(root) == {q: sorted({q, (q + 5) % N_REF}) for q in range(N_QUERY)}

    np.save(root / VPR_BENCH_GT, table[:4], allow_pickle=False)
    with pytest.raises(VPRInputError, match=r"ground_truth_new.npy: 4 rows of reference indices, but query/ holds 10"):
        open_dataset(root)


def test_vpr_benchs_true_negative_rows_are_queries_with_no_right_reference(tmp_path):
    # VPR-Bench's *_TN sets list [-1] for a query that shows no reference place
    root = vpr_bench_folder(tmp_path / "vb")
    np.save(root / VPR_BENCH_GT, object_rows([(0, [0, 1]), (1, [-1]), (2, np.array([-1])), (3, [3])]),
            allow_pickle=True)
    ds = open_dataset(root)
    assert positives(root) == {0: [0, 1], 1: [], 2: [], 3: [3], **{q: [] for q in range(4, N_QUERY)}}
    assert ds.ground_truth.known[:4].tolist() == [True, False, False, True]

    # -1 beside a real reference, or another negative index, is no marker: refused by name
    for refs, bad in (([2, -1], -1), ([-2], -2), ([-1, -1, 5], -1)):
        np.save(root / VPR_BENCH_GT, object_rows([(0, refs)]), allow_pickle=True)
        with pytest.raises(VPRInputError, match=rf"ground_truth_new.npy: row 1 points at reference {bad},"):
            open_dataset(root)


# --------------------------------------------------------------------------- odd files, one message each


def _truncated(gt: Path) -> None:
    np.save(gt, object_rows([(q, list(range(q, N_REF))) for q in range(N_QUERY)]), allow_pickle=True)
    data = gt.read_bytes()
    gt.write_bytes(data[: len(data) // 2])


def _truncated_numbers(gt: Path) -> None:
    np.save(gt, np.arange(2 * N_QUERY).reshape(N_QUERY, 2), allow_pickle=False)
    data = gt.read_bytes()
    gt.write_bytes(data[:-8])


REFUSED = {
    "0-d": (lambda gt: np.save(gt, np.array(3), allow_pickle=False), r"holds one int \(a 0-d array\)"),
    "dict": (lambda gt: np.save(gt, {"0": [0, 1]}, allow_pickle=True), r"holds one dict \(a 0-d array\)"),
    "truncated pickle": (_truncated, r"damaged or truncated"),
    "truncated numbers": (_truncated_numbers, r"truncated: its header promises an array of int64, shape \(10, 2\)"),
    "truncated header": (lambda gt: gt.write_bytes(b"\x93NUMPY\x01\x00v\x00{'descr': '<i8', "),
                         r"damaged or truncated header"),
    "truncated signature": (lambda gt: gt.write_bytes(b"\x93NUM"), r"truncated: 4 bytes"),
    "float 0.9": (lambda gt: np.save(gt, object_rows([(0, [0]), (1, [0.9])]), allow_pickle=True),
                  r"row 2: reference 0.9 is a float; indices must be integers"),
    "float 2.0": (lambda gt: np.save(gt, object_rows([(0, np.array([2.0, 3.0]))]), allow_pickle=True),
                  r"row 1: reference 2.0 is a float64; indices must be integers"),
    "float query index": (lambda gt: np.save(gt, object_rows([(0.9, [0])]), allow_pickle=True),
                          r"row 1: query index 0.9 is a float; indices must be integers"),
    "float table": (lambda gt: np.save(gt, np.array([[0.0, 1.0]] * N_QUERY), allow_pickle=False),
                    r"row 1: reference 0.0 is a float64; indices must be integers"),
    "complex": (lambda gt: np.save(gt, object_rows([(0, np.array([1 + 2j]))]), allow_pickle=True),
                r"row 1: reference \(1\+2j\) is a complex128; indices must be integers"),
    "Python complex": (lambda gt: np.save(gt, object_rows([(0, [1 + 2j])]), allow_pickle=True),
                       r"refused: its pickled data asks for builtins\.complex"),
    "NaN in a list": (lambda gt: np.save(gt, object_rows([(0, [0]), (1, [2, float("nan")])]), allow_pickle=True),
                      r"row 2: reference nan is a float; indices must be integers"),
    "NaN in an array": (lambda gt: np.save(gt, object_rows([(0, [0]), (1, np.array([2.0, np.nan]))]),
                                           allow_pickle=True),
                        r"row 2: reference nan is a float64; indices must be integers"),
    "NaN in a table": (lambda gt: np.save(gt, np.array([[0, 1]] * 5 + [[2, np.nan]] * 5), allow_pickle=False),
                       r"row 6: reference nan is a float64; indices must be integers"),
    "bool": (lambda gt: np.save(gt, object_rows([(0, [True])]), allow_pickle=True),
             r"row 1: reference True is a bool"),
    "text": (lambda gt: np.save(gt, object_rows([(0, ["3"])]), allow_pickle=True),
             r"row 1: reference '3' is text"),
    "1-d numbers": (lambda gt: np.save(gt, np.arange(N_QUERY), allow_pickle=False),
                    r"holds an array of int64, shape \(10,\), not VPR-Bench's"),
    "three columns": (lambda gt: np.save(gt, np.empty((2, 3), dtype=object), allow_pickle=True),
                      r"holds an object array of shape \(2, 3\)"),
    "bare pickle": (lambda gt: gt.write_bytes(pickle.dumps([[0, [1]]])), r"not a NumPy \.npy file.*bare Python pickle"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_an_odd_ground_truth_is_refused_by_name(tmp_path, case):
    write, message = REFUSED[case]
    root = vpr_bench_folder(tmp_path / "vb")
    write(root / VPR_BENCH_GT)
    with pytest.raises(VPRInputError) as info:
        open_dataset(root)
    text = str(info.value)
    assert text.startswith(f"{root / VPR_BENCH_GT}: ") and "\n" not in text, text
    assert re.search(message, text), text
    assert "-9223372036854775808" not in text and "Traceback" not in text


@pytest.mark.parametrize("case", ["NaN in an array", "dict", "truncated pickle"])
def test_the_command_line_refuses_an_odd_ground_truth_in_one_line(tmp_path, case):
    write, _ = REFUSED[case]
    root = vpr_bench_folder(tmp_path / "vb")
    write(root / VPR_BENCH_GT)
    result = run_cli("list", "--dataset", str(root), cwd=tmp_path)
    assert_one_error_line(result, str(root / VPR_BENCH_GT))
    assert "-9223372036854775808" not in result.stderr


def test_indices_are_never_rounded_or_wrapped():
    where = {"path": Path("gt.npy"), "where": "row 1", "what": "reference"}
    assert as_indices(np.array([[1], [2]], dtype=np.uint8), **where).tolist() == [1, 2]
    assert as_indices(np.array([], dtype=np.float64), **where).tolist() == []  # np.array([]): no references
    assert as_indices(7, **where).tolist() == [7]
    refused = [(np.array([0.5]), "reference 0.5 is a float64"), (np.array([np.inf]), "reference inf is a float64"),
               (np.array([2**63], dtype=np.uint64), "reference 9223372036854775808 is outside any image's index"),
               (2**70, "reference 1180591620717411303424 is outside any image's index"),
               ([[1, 2]], "reference [1, 2] is a list"), (None, "reference is None"), ({1: 2}, "reference is a dict")]
    for bad, says in refused:
        with pytest.raises(VPRInputError, match=re.escape(f"gt.npy: row 1: {says}")):
            as_indices(bad, **where)


# --------------------------------------------------------------------------- the package's source

PACKAGE = Path(vpr_explorer.__file__).parent
#: The one module that unpickles.
UNPICKLES = {"data/safe_npy.py"}
#: Imports pickle only to catch the error torch.load(weights_only=True) raises.
NAMES_PICKLES_ERROR = {"descriptors/runtime.py"}
PICKLE_MODULES = {"pickle", "_pickle", "cPickle", "dill", "cloudpickle", "joblib", "shelve", "marshal"}


def _is_constant(node: ast.expr | None, value: bool) -> bool:
    return isinstance(node, ast.Constant) and node.value is value


def pickle_faults(name: str, text: str) -> list[str]:
    """Every way ``text`` (module ``name`` of the package) could unpickle data it reads."""
    faults = [f"{name}: allow_pickle=True"] if "allow_pickle=True" in text.replace(" ", "") else []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import | ast.ImportFrom):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            faults += [f"{name}:{node.lineno}: imports {m}" for m in modules
                       if m.split(".")[0] in PICKLE_MODULES and name not in UNPICKLES | NAMES_PICKLES_ERROR]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "pickle":
            if name not in UNPICKLES and node.attr != "UnpicklingError":
                faults.append(f"{name}:{node.lineno}: pickle.{node.attr}")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "load":
            owner, keywords = ast.unparse(node.func.value), {k.arg: k.value for k in node.keywords}
            if owner in ("np", "numpy") and "allow_pickle" in keywords and not _is_constant(keywords["allow_pickle"],
                                                                                         False):
                faults.append(f"{name}:{node.lineno}: np.load(allow_pickle={ast.unparse(keywords['allow_pickle'])})")
            if owner == "torch" and not _is_constant(keywords.get("weights_only"), True):
                faults.append(f"{name}:{node.lineno}: torch.load without weights_only=True")
    return faults


def test_the_scan_finds_each_way_to_unpickle():
    assert pickle_faults("a.py", "np.load(p, allow_pickle=False)\ntorch.load(p, weights_only=True)") == []
    for source in ("x = np.load(p, allow_pickle = True)", "np.load(p, allow_pickle=flag)", "import pickle",
                   "from pickle import loads", "import joblib", "pickle.loads(b)", "torch.load(p)",
                   "torch.load(p, weights_only=False)"):
        assert pickle_faults("a.py", source), source
    caught = "import pickle\ntry:\n    pass\nexcept pickle.UnpicklingError:\n    pass"
    assert pickle_faults("descriptors/runtime.py", caught) == []
    assert pickle_faults("descriptors/runtime.py", "import pickle\npickle.load(f)")


def test_no_reader_in_the_package_unpickles():
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 20 and PACKAGE / "data" / "safe_npy.py" in files
    faults = [f for path in files for f in pickle_faults(path.relative_to(PACKAGE).as_posix(),
                                                          path.read_text(encoding="utf-8"))]
    assert not faults, faults
