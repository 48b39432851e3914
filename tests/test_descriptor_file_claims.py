"""Descriptor files that claim more than they hold, rows too large to square, and the file a run was made with.

* A ``.npy`` header, a ``.npz`` entry's header or an hloc ``.h5`` dataset can claim any
  shape in a few bytes; each claim is checked against the bytes the file holds (and this
  machine's memory) before anything is allocated, and refused at once with one error
  naming the file and the claimed shape. The huge claims run in a child process whose
  address space is capped, timed, with its peak memory measured.
* A row of 1e300s overflows a float64 norm, yet it is a direction like any other: it is
  normalised correctly, not reported as zero.
* ``--descriptors pixels.npz`` and the built-in ``pixels`` extractor write the same
  ``descriptor`` name; the JSON of a run on a file records its path and sha256.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from numpy.lib import format as npy_format

from images import write_noisy_route, write_random_png
from vpr_explorer.cli import main
from vpr_explorer.descriptors.imported import HLOC_KEY, load_descriptor_file, relative_names, write_descriptor_file
from vpr_explorer.errors import VPRInputError
from vpr_explorer.data.example_layouts import utm_name
from vpr_explorer.pipeline import dataset_descriptors, open_dataset

D = 8
QUICK_S = 0.5  # "at once": a refusal must take well under a second
GROWTH_LIMIT = 64 << 20  # bytes the peak memory may grow while a claim is refused
AS_HEADROOM = 1 << 30  # the child's address space: what it has mapped after its imports, plus this

REFUSE_IN_CHILD = r"""
import json, resource, sys, time
from pathlib import Path

import h5py  # noqa: F401  (imported before the address space is capped)

from vpr_explorer.descriptors.imported import load_descriptor_file
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import open_dataset

dataset = open_dataset(sys.argv[1])
mapped = int(Path("/proc/self/statm").read_text().split()[0]) * resource.getpagesize()
resource.setrlimit(resource.RLIMIT_AS, (mapped + int(sys.argv[3]), resource.getrlimit(resource.RLIMIT_AS)[1]))
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
try:
    load_descriptor_file(Path(sys.argv[2]), dataset.image_paths, dataset.root)
    error = None
except VPRInputError as exc:
    error = str(exc)
seconds = time.perf_counter() - start
grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) * 1024
print(json.dumps({"error": error, "seconds": seconds, "grown": grown}))
"""


# --- files and datasets -------------------------------------------------------------------


@pytest.fixture(scope="module")
def route(tmp_path_factory) -> Path:
    """Two traversal folders of 8 frames each: 16 images."""
    return write_noisy_route(tmp_path_factory.mktemp("claims") / "route", frames=8)


@pytest.fixture(scope="module")
def names(route) -> list[str]:
    dataset = open_dataset(route)
    return list(relative_names(dataset.image_paths, dataset.root))


@pytest.fixture(scope="module")
def database_queries(tmp_path_factory) -> Path:
    """A database/queries layout of 12 + 12 position-tagged images, 10 m apart."""
    root = tmp_path_factory.mktemp("claims") / "dq"
    for side in ("database", "queries"):
        (root / side).mkdir(parents=True)
        for f in range(12):
            write_random_png(root / side / utm_name(500000 + 10.0 * f, 6960000.0, f), seed=f, size=(32, 24))
    return root


def unit_rows(n: int, seed: int = 0) -> np.ndarray:
    rows = np.random.default_rng(seed).normal(size=(n, D))
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def npy_bytes(shape: tuple[int, ...], dtype: str = "<f4", payload: bytes = b"") -> bytes:
    """A .npy header declaring ``shape`` and ``dtype``, followed by ``payload`` (whatever its length)."""
    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue() + payload


def names_entry(names: list[str]) -> bytes:
    array = np.array(names)
    return npy_bytes(array.shape, array.dtype.str, array.tobytes())


def write_claiming_npz(path: Path, names: list[str], shape: tuple[int, ...], *, directory_agrees: bool) -> Path:
    """An .npz whose descriptors entry claims ``shape`` but holds 64 bytes; with ``directory_agrees`` the
    archive's directory records the claimed size as the entry's uncompressed size (an entry that would
    inflate to it)."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("names.npy", names_entry(names))
        archive.writestr("descriptors.npy", npy_bytes(shape, payload=b"\0" * 64))
        if directory_agrees:
            info = archive.getinfo("descriptors.npy")
            info.file_size = len(npy_bytes(shape)) + int(np.prod(shape, dtype=object)) * 4
    return path


def write_claiming_h5(path: Path, name: str, shape: tuple[int, ...], chunks: tuple[int, ...] | None) -> Path:
    """hloc's layout with one image whose descriptor claims ``shape`` and was never written."""
    with h5py.File(path, "w") as fd:
        fd.create_group(name).create_dataset(HLOC_KEY, shape=shape, dtype="f4", chunks=chunks,
                                             compression="gzip" if chunks else None)
    return path


def refuse_in_child(route: Path, path: Path) -> dict:
    """Load ``path`` in a child process capped at ``AS_HEADROOM`` more address space: its error, time and growth."""
    r = subprocess.run([sys.executable, "-c", REFUSE_IN_CHILD, str(route), str(path), str(AS_HEADROOM)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip(), r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


# --- huge claims, refused at once ----------------------------------------------------------


def test_npy_header_claiming_1e15_by_1e6_is_refused_at_once(tmp_path, route):
    path = tmp_path / "huge.npy"
    path.write_bytes(npy_bytes((10**15, 10**6), payload=b"\0" * 64))
    got = refuse_in_child(route, path)
    assert got["error"].startswith(f"{path}: cannot read it as a .npy descriptor file (its header claims shape "
                                   "(1000000000000000, 1000000) of float32"), got["error"]
    assert "but 64 bytes follow the header" in got["error"] and "write it again" in got["error"]
    assert got["seconds"] < QUICK_S and got["grown"] < GROWTH_LIMIT, got


def test_npz_entry_claiming_1e12_by_2048_is_refused_at_once(tmp_path, route, names):
    path = write_claiming_npz(tmp_path / "huge.npz", names, (10**12, 2048), directory_agrees=False)
    got = refuse_in_child(route, path)
    assert got["error"].startswith(f"{path}: cannot read it as a .npz descriptor file (descriptors.npy in the archive "
                                   "claims shape (1000000000000, 2048) of float32"), got["error"]
    assert "but the entry holds 64 bytes after its header" in got["error"]
    assert got["seconds"] < QUICK_S and got["grown"] < GROWTH_LIMIT, got


def test_npz_entry_that_would_inflate_beyond_memory_is_refused_at_once(tmp_path, route, names):
    path = write_claiming_npz(tmp_path / "bomb.npz", names, (10**12, 2048), directory_agrees=True)
    got = refuse_in_child(route, path)
    assert got["error"].startswith(f"{path}: descriptors.npy in the archive claims shape (1000000000000, 2048) of "
                                   "float32, 7.3 PiB, more than this machine's memory ("), got["error"]
    assert "write this dataset's descriptors again with np.savez" in got["error"]
    assert got["seconds"] < QUICK_S and got["grown"] < GROWTH_LIMIT, got


@pytest.mark.parametrize("shape, chunks, fragment", [
    ((2**40,), None, "claims shape (1099511627776,) of float32 (4.0 TiB), but the file stores 0 bytes for it"),
    ((2**29,), None, "claims shape (536870912,) of float32 (2.0 GiB), but the file stores 0 bytes for it"),
    ((2**29,), (2**16,), "claims shape (536870912,) of float32 (2.0 GiB), but only 0 of its 8,192 chunks are "
                         "written"),
], ids=["2^40-contiguous", "2GiB-contiguous", "2GiB-chunked-gzip"])
def test_h5_dataset_claiming_more_than_the_file_holds_is_refused_at_once(tmp_path, route, names, shape, chunks,
                                                                        fragment):
    path = write_claiming_h5(tmp_path / "huge.h5", names[0], shape, chunks)
    assert path.stat().st_size < 8192  # a few KB claiming GB or TB
    got = refuse_in_child(route, path)
    assert got["error"].startswith(f"{path}: {names[0]}/{HLOC_KEY} {fragment}"), got["error"]
    assert "write the descriptors again" in got["error"]
    assert got["seconds"] < QUICK_S and got["grown"] < GROWTH_LIMIT, got


@pytest.mark.parametrize("dataset, suffix", [("database_queries", ".npy"), ("route", ".npz"), ("route", ".h5")])
def test_cli_refuses_a_huge_claim_on_one_line(tmp_path, request, names, dataset, suffix):
    root = request.getfixturevalue(dataset)
    path = tmp_path / f"bad{suffix}"
    if suffix == ".npy":  # a database/queries layout first reads a .npy's shape, to decide on memory-mapping it
        path.write_bytes(npy_bytes((10**15, 10**6), payload=b"\0" * 64))
    elif suffix == ".npz":
        write_claiming_npz(path, names, (10**12, 2048), directory_agrees=False)
    else:
        write_claiming_h5(path, names[0], (2**40,), None)
    places = ["--group", "1", "--step", "1"] if dataset == "route" else []  # 8 frames per traversal
    r = subprocess.run([sys.executable, "-m", "vpr_explorer.cli", "evaluate", "--dataset", str(root), *places,
                        "--descriptors", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    lines = r.stderr.strip().split("\n")
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: "), r.stderr
    assert ("(1000000000000000, 1000000)", "(1000000000000, 2048)", "(1099511627776,)")[(".npy", ".npz", ".h5")
                                                                                        .index(suffix)] in lines[0]


# --- boundaries: exactly the bytes claimed loads; one byte off is refused -----------------------


def test_npy_with_exactly_the_claimed_bytes_loads_and_one_byte_off_is_refused(tmp_path, route):
    dataset = open_dataset(route)
    rows = unit_rows(16).astype("<f4")
    path = tmp_path / "d.npy"
    exact = npy_bytes(rows.shape, "<f4", rows.tobytes())
    path.write_bytes(exact)
    got = load_descriptor_file(path, dataset.image_paths, dataset.root)
    np.testing.assert_array_equal(got.descriptors, rows)
    for broken, held in ((exact[:-1], "511 bytes"), (exact + b"\0", "513 bytes")):
        path.write_bytes(broken)
        with pytest.raises(VPRInputError, match=rf"d\.npy: cannot read it as a \.npy descriptor file \(its header "
                                                rf"claims shape \(16, 8\) of float32, 512 bytes, but {held} follow "
                                                r"the header\); the file is truncated, damaged"):
            load_descriptor_file(path, dataset.image_paths, dataset.root)


def test_npz_entry_one_row_short_of_its_claim_is_refused(tmp_path, route, names):
    dataset = open_dataset(route)
    rows = unit_rows(16).astype("<f4")
    path = tmp_path / "d.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("names.npy", names_entry(names))
        archive.writestr("descriptors.npy", npy_bytes((17, D), "<f4", rows.tobytes()))
    with pytest.raises(VPRInputError, match=r"d\.npz: cannot read it as a \.npz descriptor file \(descriptors\.npy "
                                            r"in the archive claims shape \(17, 8\) of float32, 544 bytes, but the "
                                            r"entry holds 512 bytes after its header\)"):
        load_descriptor_file(path, dataset.image_paths, dataset.root)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:  # the same, compressed and exact: loads
        archive.writestr("names.npy", names_entry(names))
        archive.writestr("descriptors.npy", npy_bytes((16, D), "<f4", rows.tobytes()))
    np.testing.assert_array_equal(load_descriptor_file(path, dataset.image_paths, dataset.root).descriptors, rows)


def test_npz_entry_that_is_not_a_npy_array_is_refused(tmp_path, route, names):
    dataset = open_dataset(route)
    path = tmp_path / "d.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("names.npy", names_entry(names))
        archive.writestr("descriptors", b"\0" * 512)  # np.load would hand back these bytes as the array
    with pytest.raises(VPRInputError, match=r"d\.npz: cannot read it as a \.npz descriptor file \(the archive's "
                                            r"entry 'descriptors' is not a \.npy array"):
        load_descriptor_file(path, dataset.image_paths, dataset.root)


def test_h5_chunked_descriptors_load_when_every_chunk_is_written(tmp_path, route, names):
    dataset = open_dataset(route)
    rows = unit_rows(16).astype("f4")
    path = tmp_path / "d.h5"
    with h5py.File(path, "w") as fd:
        for i, (name, row) in enumerate(zip(names, rows)):
            target = fd.create_group(name).create_dataset(HLOC_KEY, shape=(D,), dtype="f4", chunks=(D // 2,),
                                                          compression="gzip")
            if i == 5:
                target[: D // 2] = row[: D // 2]  # half of it: its second chunk is never written
            else:
                target[...] = row
    with pytest.raises(VPRInputError, match=rf"d\.h5: {names[5]}/{HLOC_KEY} claims shape \(8,\) of float32 \(32 "
                                            r"bytes\), but only 1 of its 2 chunks are written"):
        load_descriptor_file(path, dataset.image_paths, dataset.root)
    with h5py.File(path, "a") as fd:
        fd[f"{names[5]}/{HLOC_KEY}"][...] = rows[5]
    np.testing.assert_array_equal(load_descriptor_file(path, dataset.image_paths, dataset.root).descriptors, rows)


@pytest.mark.parametrize("kind", ["external", "virtual"])
def test_h5_dataset_stored_in_another_file_is_not_read(tmp_path, route, names, kind):
    dataset = open_dataset(route)
    rows = unit_rows(16).astype("f4")
    outside = tmp_path / "elsewhere.bin"
    rows[0].tofile(outside)
    with h5py.File(tmp_path / "elsewhere.h5", "w") as fd:
        fd.create_dataset("row", data=rows[0])
    path = tmp_path / "d.h5"
    with h5py.File(path, "w") as fd:
        for i, (name, row) in enumerate(zip(names, rows)):
            group = fd.create_group(name)
            if i > 0:
                group.create_dataset(HLOC_KEY, data=row)
            elif kind == "external":  # raw bytes of another file
                group.create_dataset(HLOC_KEY, shape=(D,), dtype="f4", external=[(str(outside), 0, 4 * D)])
            else:  # a view of another HDF5 file
                layout = h5py.VirtualLayout(shape=(D,), dtype="f4")
                layout[:] = h5py.VirtualSource(str(tmp_path / "elsewhere.h5"), "row", shape=(D,))
                group.create_virtual_dataset(HLOC_KEY, layout)
    with h5py.File(path, "r") as fd:  # HDF5 itself would read the other file's values
        np.testing.assert_array_equal(fd[f"{names[0]}/{HLOC_KEY}"][()], rows[0])
    with pytest.raises(VPRInputError, match=rf"d\.h5: {names[0]}/{HLOC_KEY} keeps its values in other files \(an "
                                            rf"HDF5 {kind} dataset\), which are not read"):
        load_descriptor_file(path, dataset.image_paths, dataset.root)


# --- rows of 1e300 -------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_rows_of_1e300_are_normalised_not_called_zero(tmp_path, route, names, dtype):
    dataset = open_dataset(route)
    rows = unit_rows(16)
    rows[3] = 1e300
    rows[7] = 0.0
    rows[7, :2] = (3e300, -4e300)
    rows[9] = rows[9] * 1e307  # finite, with a norm above float64's largest
    path = tmp_path / "big.npz"
    np.savez(path, names=np.array(names), descriptors=rows)
    got = load_descriptor_file(path, dataset.image_paths, dataset.root, dtype=dtype)
    want = unit_rows(16)
    want[3] = 1 / np.sqrt(D)
    want[7] = 0.0
    want[7, :2] = (0.6, -0.8)
    tol = 1e-3 if dtype == "float16" else 1e-7
    np.testing.assert_allclose(got.descriptors.astype(np.float64), want, atol=tol, rtol=0)
    assert got.descriptors.dtype == dtype
    assert any("3 of 16 rows were rescaled" in n for n in got.notes), got.notes


def test_tiny_rows_are_refused_by_their_norm_and_zero_rows_as_zero(tmp_path, route, names):
    dataset = open_dataset(route)
    rows = unit_rows(16)
    rows[2] = 1e-20
    rows[4] = 0.0
    path = tmp_path / "small.npz"
    np.savez(path, names=np.array(names), descriptors=rows)
    with pytest.raises(VPRInputError, match=rf"small\.npz: of the descriptors, 1 are all zero \({names[4]}\) and 1 "
                                            rf"have a norm below 1e-12, too close to zero to trust their direction "
                                            rf"\({names[2]}\)"):
        load_descriptor_file(path, dataset.image_paths, dataset.root)


def test_evaluating_rows_of_1e300_equals_evaluating_their_directions(tmp_path, route, names):
    rows = unit_rows(16, seed=3)
    np.savez(tmp_path / "unit.npz", names=np.array(names), descriptors=rows)
    scaled = rows.copy()
    scaled[[1, 6, 12]] *= 1e300
    np.savez(tmp_path / "scaled.npz", names=np.array(names), descriptors=scaled)
    for stem in ("unit", "scaled"):
        assert main(["evaluate", "--dataset", str(route), "--descriptors", str(tmp_path / f"{stem}.npz"),
                     "--group", "1", "--step", "1", "--runs", "2", "--json", str(tmp_path / f"{stem}.json")]) == 0
    unit, big = (json.loads((tmp_path / f"{s}.json").read_text()) for s in ("unit", "scaled"))
    assert big["methods"] == unit["methods"]


# --- the JSON records the descriptor file --------------------------------------------------


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_json_tells_a_descriptor_file_from_the_extractor_it_is_named_after(tmp_path, route, monkeypatch):
    dataset = open_dataset(route)
    cache = tmp_path / "cache"
    pixels = dataset_descriptors(dataset, "pixels", cache_root=cache)
    path = tmp_path / "pixels.npz"
    write_descriptor_file(path, pixels, dataset.image_paths, dataset.root)
    monkeypatch.chdir(tmp_path)  # the file given by a relative path: the JSON records it absolute
    common = ["--dataset", str(route), "--group", "1", "--step", "1", "--runs", "2"]
    assert main(["evaluate", *common, "--descriptors", "pixels.npz", "--json", "file.json"]) == 0
    assert main(["evaluate", *common, "--descriptor", "pixels", "--cache-dir", str(cache),
                 "--json", "builtin.json"]) == 0
    from_file, builtin = (json.loads((tmp_path / f"{s}.json").read_text()) for s in ("file", "builtin"))
    assert from_file["settings"]["descriptor"] == builtin["settings"]["descriptor"] == "pixels"
    assert from_file["settings"]["descriptors_file"] == str(path)
    assert from_file["settings"]["descriptors_sha256"] == _sha256(path)
    assert "descriptors_file" not in builtin["settings"] and "descriptors_sha256" not in builtin["settings"]
    rest = {k: v for k, v in from_file["settings"].items() if k not in ("descriptors_file", "descriptors_sha256")}
    assert rest == builtin["settings"]
    assert from_file["methods"] == builtin["methods"]  # the same vectors: only the settings tell the runs apart


def test_json_of_a_benchmark_layout_and_a_sweep_record_the_file(tmp_path, route, database_queries):
    retrieval = open_dataset(database_queries)
    path = tmp_path / "netvlad.h5"
    write_descriptor_file(path, dataset_descriptors(retrieval, "pixels", cache_root=tmp_path / "cache"),
                          retrieval.image_paths, retrieval.root)
    assert main(["evaluate", "--dataset", str(database_queries), "--descriptors", str(path),
                 "--json", str(tmp_path / "dq.json")]) == 0
    settings = json.loads((tmp_path / "dq.json").read_text())["settings"]
    assert (settings["descriptor"], settings["descriptors_file"], settings["descriptors_sha256"]) == (
        "netvlad", str(path), _sha256(path))

    traversals = open_dataset(route)
    npy = tmp_path / "rows.npy"
    written = write_descriptor_file(npy, unit_rows(16), traversals.image_paths, traversals.root)  # with rows.txt
    assert main(["sweep", "--dataset", str(route), "--descriptors", str(npy), "--groups", "1", "2", "--steps", "1",
                 "--runs", "2", "--json", str(tmp_path / "s.json"), "--csv", str(tmp_path / "s.csv")]) == 0
    want = {"descriptors_file": str(npy), "descriptors_sha256": _sha256(npy),
            "names_file": str(written[1]), "names_sha256": _sha256(written[1])}
    settings = json.loads((tmp_path / "s.json").read_text())["settings"]
    assert {k: settings.get(k) for k in want} == want and settings["descriptor"] == "rows"
    rows = list(csv.DictReader(io.StringIO((tmp_path / "s.csv").read_text())))
    assert rows and all({k: row[k] for k in want} == want for row in rows)
