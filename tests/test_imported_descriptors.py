"""Descriptor files made elsewhere (.npz, .npy + names, hloc .h5): round trips, name matching, every refusal.

GardensPoint's pixel descriptors, computed by the project, are written in a shuffled row
order and read back: they must come back bit for bit in the dataset's image order.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from vpr_explorer.descriptors.imported import (
    HLOC_KEY,
    DescriptorFormat,
    load_descriptor_file,
    relative_names,
    write_descriptor_file,
)
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import paper_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.method.places import PlaceSpec, make_places

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def perm() -> np.ndarray:
    """A shuffled row order: files never list rows in the dataset's order by accident."""
    return np.random.default_rng(11).permutation(600)


@pytest.fixture(scope="module")
def names(gardens_point) -> list[str]:
    return list(relative_names(gardens_point.image_paths, gardens_point.root))


def write_npz(path: Path, rows: np.ndarray, names) -> Path:
    np.savez(path, names=np.array(list(names), dtype=str), descriptors=rows)
    return path


def write_h5(path: Path, rows: np.ndarray, names) -> Path:
    with h5py.File(path, "w") as fd:
        for name, row in zip(names, rows):
            fd.create_group(name).create_dataset(HLOC_KEY, data=row)
    return path


def load(path, gardens_point, **kw):
    return load_descriptor_file(path, gardens_point.image_paths, gardens_point.root, **kw)


def shuffled(gp_pixels, names, perm):
    return gp_pixels[perm], [names[i] for i in perm]


# --- round trips ------------------------------------------------------------------------


@pytest.mark.parametrize("suffix, source", [(".npz", DescriptorFormat.NPZ), (".npy", DescriptorFormat.NPY),
                                            (".h5", DescriptorFormat.HLOC), (".hdf5", DescriptorFormat.HLOC)])
def test_round_trip_in_shuffled_order_is_exact(tmp_path, gardens_point, gp_pixels, perm, suffix, source):
    path = tmp_path / f"pixels-elsewhere{suffix}"
    written = write_descriptor_file(path, gp_pixels[perm], [gardens_point.image_paths[i] for i in perm],
                                    gardens_point.root)
    assert written[0] == path
    got = load(path, gardens_point)
    assert got.descriptors.dtype == np.float32
    assert np.array_equal(got.descriptors, gp_pixels)
    assert not got.descriptors.flags.writeable
    assert (got.name, got.source, got.path, got.n_images, got.dim) == ("pixels-elsewhere", source, path, 600, 2048)
    assert any("L2-normalised after the checks" in n and "kept as stored" in n for n in got.notes)
    if source is DescriptorFormat.NPY:
        assert written == (path, path.with_suffix(".txt")) and got.names_file == path.with_suffix(".txt")


def test_hloc_file_has_nested_groups_that_hlocs_name_listing_reads(tmp_path, gardens_point, gp_pixels, names, perm):
    path = write_h5(tmp_path / "global-feats-pixels.h5", *shuffled(gp_pixels, names, perm))
    with h5py.File(path, "r") as fd:
        assert isinstance(fd["day_left"], h5py.Group) and isinstance(fd["day_left/Image000.jpg"], h5py.Group)
        assert fd["day_left/Image000.jpg/global_descriptor"].shape == (2048,)
        listed = []  # hloc.utils.io.list_h5_names
        fd.visititems(lambda _, obj: listed.append(obj.parent.name.strip("/")) if isinstance(obj, h5py.Dataset)
                      else None)
    assert sorted(listed) == sorted(names)
    assert np.array_equal(load(path, gardens_point).descriptors, gp_pixels)


def test_hloc_float16_and_extra_datasets_per_group(tmp_path, gardens_point, gp_pixels, names):
    """hloc stores float16 by default and an ``image_size`` beside each descriptor."""
    path = tmp_path / "netvlad.h5"
    with h5py.File(path, "w") as fd:
        for name, row in zip(names, gp_pixels):
            group = fd.create_group(name)
            group.create_dataset(HLOC_KEY, data=row.astype(np.float16)[None])  # (1, D) too
            group.create_dataset("image_size", data=np.array([640, 480]))
    got = load(path, gardens_point)
    np.testing.assert_allclose(got.descriptors, gp_pixels, atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(got.descriptors, axis=1), 1, atol=1e-6)
    assert any("stored as float16" in n for n in got.notes)


def test_npy_without_names_is_in_dataset_order(tmp_path, gardens_point, gp_pixels):
    path = tmp_path / "plain.npy"
    np.save(path, gp_pixels)
    got = load(path, gardens_point)
    assert np.array_equal(got.descriptors, gp_pixels) and got.names_file is None
    assert any("dataset's image order" in n for n in got.notes)


def test_npy_names_file_beside_or_given(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    np.save(tmp_path / "cosplace.npy", rows)
    (tmp_path / "cosplace_names.txt").write_text("\n".join(order) + "\n\n")
    got = load(tmp_path / "cosplace.npy", gardens_point)
    assert np.array_equal(got.descriptors, gp_pixels) and got.names_file == tmp_path / "cosplace_names.txt"

    elsewhere = tmp_path / "lists" / "order.txt"
    elsewhere.parent.mkdir()
    shutil.move(tmp_path / "cosplace_names.txt", elsewhere)
    assert np.array_equal(load(tmp_path / "cosplace.npy", gardens_point, names_file=elsewhere).descriptors,
                          gp_pixels)
    with pytest.raises(VPRInputError, match=r"missing\.txt: the names file does not exist"):
        load(tmp_path / "cosplace.npy", gardens_point, names_file=tmp_path / "missing.txt")

    shutil.copy(elsewhere, tmp_path / "cosplace.txt")
    shutil.copy(elsewhere, tmp_path / "cosplace_names.txt")
    with pytest.raises(VPRInputError, match=r"two names files beside it \(cosplace\.txt and cosplace_names\.txt\)"):
        load(tmp_path / "cosplace.npy", gardens_point)


def test_float16(tmp_path, gardens_point, gp_pixels, names, perm):
    path = write_npz(tmp_path / "d.npz", *shuffled(gp_pixels, names, perm))
    half = load(path, gardens_point, dtype="float16")
    assert half.descriptors.dtype == np.float16
    assert np.array_equal(half.descriptors, gp_pixels.astype(np.float16))
    assert half.key != load(path, gardens_point).key
    with pytest.raises(VPRInputError, match="dtype='float64' is not a descriptor dtype"):
        load(path, gardens_point, dtype="float64")


def test_key_follows_content(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    path = write_npz(tmp_path / "d.npz", rows, order)
    first = load(path, gardens_point)
    assert load(path, gardens_point).key == first.key  # same bytes, same key
    assert len(first.key) == 64
    changed = rows.copy()
    changed[0, 0] += 0.5
    write_npz(path, changed, order)
    again = load(path, gardens_point)
    assert again.key != first.key and not np.array_equal(again.descriptors, first.descriptors)

    # a .npy's names file is part of its content: swapping two names swaps two rows
    np.save(tmp_path / "e.npy", rows)
    (tmp_path / "e.txt").write_text("\n".join(order))
    before = load(tmp_path / "e.npy", gardens_point)
    (tmp_path / "e.txt").write_text("\n".join([order[1], order[0], *order[2:]]))
    after = load(tmp_path / "e.npy", gardens_point)
    assert after.key != before.key and not np.array_equal(after.descriptors, before.descriptors)


def test_rows_off_unit_length_are_normalised(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    scale = np.linspace(0.5, 40, len(rows))[:, None]
    path = write_npz(tmp_path / "raw.npz", rows.astype(np.float64) * scale, order)
    got = load(path, gardens_point)
    assert got.descriptors.dtype == np.float32
    np.testing.assert_allclose(got.descriptors, gp_pixels, atol=1e-7)
    assert any("rows were rescaled to unit length" in n for n in got.notes)


# --- name matching ----------------------------------------------------------------------


@pytest.mark.parametrize("prefix", ["GardensPointWalking/", "/home/someone/data/GardensPointWalking/"])
def test_names_with_leading_folders_match_their_tail(tmp_path, gardens_point, gp_pixels, names, perm, prefix):
    rows, order = shuffled(gp_pixels, names, perm)
    got = load(write_npz(tmp_path / "d.npz", rows, [prefix + n for n in order]), gardens_point)
    assert np.array_equal(got.descriptors, gp_pixels)
    assert any("600 names matched by dropping leading folders" in n for n in got.notes)


def test_windows_and_dot_slash_names_match_exactly(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    odd = [n.replace("/", "\\") if i % 2 else "./" + n for i, n in enumerate(order)]
    got = load(write_npz(tmp_path / "d.npz", rows, odd), gardens_point)
    assert np.array_equal(got.descriptors, gp_pixels)
    assert not any("matched" in n for n in got.notes)


def test_bare_file_names_match_when_unique_in_the_dataset(tmp_path, gardens_point, gp_pixels, names, perm):
    day_left = gardens_point.image_paths[:200]  # Image000.jpg ... once each
    keep = perm[perm < 200]
    path = write_npz(tmp_path / "d.npz", gp_pixels[keep], [names[i].split("/")[-1] for i in keep])
    got = load_descriptor_file(path, day_left, gardens_point.root)
    assert np.array_equal(got.descriptors, gp_pixels[:200])
    assert any("200 names matched on the file name alone, each unique in the dataset" in n for n in got.notes)

    # over all 600 images every file name is there three times: no guessing
    with pytest.raises(VPRInputError, match="600 images have no descriptor in the file .* and 200 names in the "
                                            "file are not images of the dataset"):
        load(path, gardens_point)


# --- refusals ---------------------------------------------------------------------------


def test_missing_images_are_listed(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    path = write_npz(tmp_path / "d.npz", rows[7:], order[7:])
    with pytest.raises(VPRInputError) as err:
        load(path, gardens_point)
    message = str(err.value)
    assert message.startswith(f"{path}: 7 of the dataset's 600 images have no descriptor in the file: ")
    assert "and 2 more" in message and "open the dataset the file was made for" in message
    listed = message.split("in the file: ")[1].split(" and 2 more")[0].split(", ")
    assert listed == [n for n in names if n in set(order[:7])][:5]  # in the dataset's order


def test_extra_names_are_listed(tmp_path, gardens_point, gp_pixels, names, perm):
    rows, order = shuffled(gp_pixels, names, perm)
    extra = rows[:3]
    path = write_npz(tmp_path / "d.npz", np.concatenate([rows, extra]),
                     [*order, "elsewhere/a.jpg", "elsewhere/b.jpg", "c.png"])
    with pytest.raises(VPRInputError, match=r"d\.npz: 3 names in the file are not images of the dataset: "
                                            r"elsewhere/a\.jpg, elsewhere/b\.jpg, c\.png; names are matched as "
                                            r"paths relative to .*GardensPointWalking, like 'day_left/Image000\.jpg'"):
        load(path, gardens_point)


def test_duplicate_names_are_refused(tmp_path, gardens_point, gp_pixels, names):
    path = write_npz(tmp_path / "d.npz", np.concatenate([gp_pixels, gp_pixels[:1]]), [*names, names[0]])
    with pytest.raises(VPRInputError, match=r"1 names appear more than once \(day_left/Image000\.jpg\)"):
        load(path, gardens_point)
    clash = [*names[1:], "GardensPointWalking/" + names[1]]
    path = write_npz(tmp_path / "d.npz", gp_pixels, clash)
    with pytest.raises(VPRInputError, match="both match the image day_left/Image001.jpg"):
        load(path, gardens_point)


@pytest.mark.parametrize("bad, word", [(np.nan, "NaN or infinite"), (np.inf, "NaN or infinite"), (0.0, "all zero")])
@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_nan_infinite_and_zero_rows_name_their_images(tmp_path, gardens_point, gp_pixels, names, perm, bad, word,
                                                      suffix):
    rows, order = shuffled(gp_pixels, names, perm)
    rows = rows.copy()
    victims = [order.index("night_right/Image042.jpg"), order.index("day_left/Image005.jpg")]
    rows[victims, :] = 0.0
    rows[victims, 7] = bad
    path = (write_npz if suffix == ".npz" else write_h5)(tmp_path / f"d{suffix}", rows, order)
    with pytest.raises(VPRInputError, match=f"of the descriptors, 2 are {word} "
                                            r"\(day_left/Image005\.jpg, night_right/Image042\.jpg\); "
                                            "such a row has no direction"):
        load(path, gardens_point)


def test_nan_and_zero_together(tmp_path, gardens_point, gp_pixels, names):
    rows = gp_pixels.copy()
    rows[3, 0], rows[4] = np.nan, 0.0
    with pytest.raises(VPRInputError, match=r"1 are NaN or infinite \(day_left/Image003\.jpg\) and 1 are all zero "
                                            r"\(day_left/Image004\.jpg\)"):
        load(write_npz(tmp_path / "d.npz", rows, names), gardens_point)


def test_dimension_mismatch(tmp_path, gardens_point, gp_pixels, names):
    path = tmp_path / "d.h5"
    with h5py.File(path, "w") as fd:
        for i, (name, row) in enumerate(zip(names, gp_pixels)):
            fd.create_group(name).create_dataset(HLOC_KEY, data=row[:1024] if i in (10, 300) else row)
    with pytest.raises(VPRInputError, match=r"descriptors of different lengths: 2,048 for 598 images, 1,024 for 2 "
                                            r"\(day_left/Image010\.jpg, day_right/Image100\.jpg\)"):
        load(path, gardens_point)
    np.savez(tmp_path / "d.npz", names=np.array(names), descriptors=gp_pixels.reshape(600, 2, 1024))
    with pytest.raises(VPRInputError, match=r"'descriptors' has shape \(600, 2, 1024\); expected \(n_images, D\)"):
        load(tmp_path / "d.npz", gardens_point)
    np.save(tmp_path / "v.npy", gp_pixels[:, :0])
    with pytest.raises(VPRInputError, match=r"the array has shape \(600, 0\)"):
        load(tmp_path / "v.npy", gardens_point)


def test_wrong_count(tmp_path, gardens_point, gp_pixels, names):
    np.save(tmp_path / "plain.npy", gp_pixels[:599])
    with pytest.raises(VPRInputError, match=r"plain\.npy: 599 rows for the dataset's 600 images; a \.npy without "
                                            r"names needs one row per image .*\(plain\.txt, one path relative to "):
        load(tmp_path / "plain.npy", gardens_point)
    (tmp_path / "plain.txt").write_text("\n".join(names))
    with pytest.raises(VPRInputError, match=r"599 rows but plain\.txt lists 600 names"):
        load(tmp_path / "plain.npy", gardens_point)
    np.savez(tmp_path / "d.npz", names=np.array(names[:598]), descriptors=gp_pixels)
    with pytest.raises(VPRInputError, match="598 names but 600 rows in 'descriptors'"):
        load(tmp_path / "d.npz", gardens_point)


@pytest.mark.parametrize("suffix", [".npz", ".npy", ".h5"])
def test_truncated_or_garbage_files(tmp_path, gardens_point, gp_pixels, names, suffix):
    path = tmp_path / f"d{suffix}"
    write_descriptor_file(path, gp_pixels, gardens_point.image_paths, gardens_point.root, with_names=False)
    data = path.read_bytes()
    for broken in (data[: len(data) // 2], data[:100], b"", b"not a descriptor file at all\n" * 50):
        path.write_bytes(broken)
        with pytest.raises(VPRInputError, match=f"d\\{suffix}: cannot read it as a \\{suffix} descriptor file "
                                                r"\(.*\); the file is truncated, damaged or not of that format"):
            load(path, gardens_point)


def test_wrong_kind_of_file_or_argument(tmp_path, gardens_point, gp_pixels, names):
    with pytest.raises(VPRInputError, match=r"d\.csv: unknown descriptor file extension '\.csv': give a \.npz, "
                                            r"\.npy, \.h5, \.hdf5 file"):
        load(tmp_path / "d.csv", gardens_point)
    with pytest.raises(VPRInputError, match=r"d\.npz: does not exist"):
        load(tmp_path / "d.npz", gardens_point)
    path = write_npz(tmp_path / "d.npz", gp_pixels, names)
    with pytest.raises(VPRInputError, match="only a .npy takes a names file"):
        load(path, gardens_point, names_file=tmp_path / "names.txt")
    np.savez(tmp_path / "other.npz", vectors=gp_pixels)
    with pytest.raises(VPRInputError, match=r"the \.npz holds 'vectors', not 'names' and 'descriptors'"):
        load(tmp_path / "other.npz", gardens_point)
    np.savez(tmp_path / "objects.npz", names=np.array(names, dtype=object), descriptors=gp_pixels)
    with pytest.raises(VPRInputError, match="an array holds Python objects"):
        load(tmp_path / "objects.npz", gardens_point)
    np.savez(tmp_path / "text.npz", names=np.array(names), descriptors=np.array(names))
    with pytest.raises(VPRInputError, match="'descriptors' holds <U.* values; descriptors must be real numbers"):
        load(tmp_path / "text.npz", gardens_point)
    with h5py.File(tmp_path / "local.h5", "w") as fd:
        fd.create_group(names[0]).create_dataset("keypoints", data=np.zeros((5, 2)))
    with pytest.raises(VPRInputError, match=r"no 'global_descriptor' dataset in the HDF5 file "
                                            r"\(it holds 'keypoints'\)"):
        load(tmp_path / "local.h5", gardens_point)
    with pytest.raises(VPRInputError, match=r"image_paths: day_left/Image000\.jpg listed more than once"):
        load_descriptor_file(path, [*gardens_point.image_paths, gardens_point.image_paths[0]], gardens_point.root)


def test_images_outside_the_root_are_named_by_their_whole_path(tmp_path, gardens_point, gp_pixels, names):
    outside = gardens_point.image_paths[0].resolve()
    root = tmp_path / "elsewhere"
    images = [outside, *(root / n for n in names[1:])]
    assert relative_names(images, root) == (outside.as_posix(), *names[1:])
    path = write_npz(tmp_path / "d.npz", gp_pixels[::-1], relative_names(images, root)[::-1])
    assert np.array_equal(load_descriptor_file(path, images, root).descriptors, gp_pixels)


def test_writer_refuses_bad_shapes(tmp_path, gardens_point, gp_pixels):
    with pytest.raises(VPRInputError, match=r"shape \(599, 2048\) for 600 images"):
        write_descriptor_file(tmp_path / "d.npz", gp_pixels[:599], gardens_point.image_paths, gardens_point.root)
    with pytest.raises(VPRInputError, match="unknown descriptor file extension"):
        write_descriptor_file(tmp_path / "d.mat", gp_pixels, gardens_point.image_paths, gardens_point.root)
    with pytest.raises(VPRInputError, match="descriptors: <U.* values"):
        write_descriptor_file(tmp_path / "d.npz", np.full((600, 2), "x"), gardens_point.image_paths,
                              gardens_point.root)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "d_names.txt").write_text("old")
    with pytest.raises(VPRInputError, match=r"d_names\.txt: a names file is already beside d\.npy"):
        write_descriptor_file(tmp_path / "d.npy", gp_pixels, gardens_point.image_paths, gardens_point.root)
    (tmp_path / "d_names.txt").rename(tmp_path / "d.txt")
    with pytest.raises(VPRInputError, match=r"d\.txt: a names file is already beside d\.npy"):
        write_descriptor_file(tmp_path / "d.npy", gp_pixels, gardens_point.image_paths, gardens_point.root,
                              with_names=False)
    assert write_descriptor_file(tmp_path / "d.npy", gp_pixels, gardens_point.image_paths, gardens_point.root) == (
        tmp_path / "d.npy", tmp_path / "d.txt")  # its own names file is replaced
    with pytest.raises(VPRInputError, match="cannot write the file"):
        write_descriptor_file(tmp_path / "no" / "d.h5", gp_pixels, gardens_point.image_paths, gardens_point.root)


# --- the numbers ------------------------------------------------------------------------


def test_paper_protocol_on_imported_descriptors_gives_the_same_numbers(tmp_path, gardens_point, gp_pixels, names,
                                                                        perm):
    got = load(write_h5(tmp_path / "d.h5", *shuffled(gp_pixels, names, perm)), gardens_point)
    places = make_places(gardens_point, PlaceSpec(3, 10))
    args = (places.image_place, gardens_point.image_traversal, places.n_places)
    ours = paper_protocol(gp_pixels, *args, ProtocolOptions(runs=3, seed=1))
    theirs = paper_protocol(got.descriptors, *args, ProtocolOptions(runs=3, seed=1))
    assert theirs.same_numbers(ours)
