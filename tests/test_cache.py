"""The on-disk descriptor cache: hits, content keying, damage detection, failed runs, concurrency."""

from __future__ import annotations

import hashlib
import json
import threading
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from images import write_random_png
from PIL import Image

from vpr_explorer.descriptors import DescriptorCache, DescriptorCacheWarning, Extractor, extract_descriptors
from vpr_explorer.descriptors.extract import renormalise_in_place
from vpr_explorer.descriptors.pixels import PixelsExtractor
from vpr_explorer.errors import VPRInputError


class CountingExtractor(PixelsExtractor):
    """The pixels descriptor, recording which images it decoded and how many rows it ran."""

    name = "counting-pixels"
    version = "test"

    def __init__(self) -> None:
        self.loaded: list[Path] = []
        self.forwarded = 0
        self._lock = threading.Lock()

    def load(self, path: Path) -> np.ndarray:
        with self._lock:
            self.loaded.append(Path(path))
        return super().load(path)

    def forward(self, batch: np.ndarray) -> np.ndarray:
        self.forwarded += len(batch)
        return super().forward(batch)


def write_image(path: Path, seed: int, size: tuple[int, int] = (96, 48)) -> Path:
    return write_random_png(path, seed, size)


@pytest.fixture
def images(tmp_path: Path) -> list[Path]:
    folder = tmp_path / "images"
    folder.mkdir()
    return [write_image(folder / f"img{i:02d}.png", seed=i) for i in range(10)]


@pytest.fixture
def cache(tmp_path: Path) -> DescriptorCache:
    return DescriptorCache(tmp_path / "cache")


def fresh(paths: list[Path]) -> np.ndarray:
    """Descriptors computed with no cache at all: the reference a cached run must equal."""
    return extract_descriptors(paths, PixelsExtractor())


def only_shard(cache: DescriptorCache, key: str) -> Path:
    (manifest,) = sorted((cache.folder / key).glob("*.json"))
    return manifest


# ------------------------------------------------------------------ hits and misses


def test_second_run_decodes_and_forwards_nothing(images, cache):
    first = CountingExtractor()
    a = extract_descriptors(images, first, cache=cache, batch_size=4)
    assert first.forwarded == len(images) and len(first.loaded) == len(images)
    again = CountingExtractor()
    b = extract_descriptors(images, again, cache=cache, batch_size=4)
    assert again.forwarded == 0 and again.loaded == []
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, fresh(images))
    stats = cache.stats()
    assert stats["shards"] == 1 and stats["vectors"] == len(images)


def test_renamed_and_reordered_images_are_hits(images, cache, tmp_path):
    a = extract_descriptors(images, CountingExtractor(), cache=cache)
    moved = tmp_path / "moved"
    moved.mkdir()
    order = [3, 1, 4, 0, 9, 2, 6, 5, 8, 7]
    renamed = []
    for k, i in enumerate(order):
        target = moved / f"renamed_{k}.png"
        target.write_bytes(images[i].read_bytes())
        renamed.append(target)
    counting = CountingExtractor()
    b = extract_descriptors(renamed, counting, cache=cache)
    assert counting.forwarded == 0
    np.testing.assert_array_equal(b, a[order])


def test_changed_image_is_the_only_one_recomputed(images, cache):
    a = extract_descriptors(images, CountingExtractor(), cache=cache)
    write_image(images[6], seed=1000)  # same name, other pixels
    counting = CountingExtractor()
    b = extract_descriptors(images, counting, cache=cache)
    assert counting.loaded == [images[6]] and counting.forwarded == 1
    unchanged = np.arange(len(images)) != 6
    np.testing.assert_array_equal(b[unchanged], a[unchanged])
    assert not np.allclose(b[6], a[6])
    np.testing.assert_array_equal(b, fresh(images))


def test_identical_files_are_computed_once(images, cache, tmp_path):
    twin = tmp_path / "twin.png"
    twin.write_bytes(images[2].read_bytes())
    counting = CountingExtractor()
    d = extract_descriptors([images[2], twin, images[2], images[5]], counting, cache=cache)
    assert counting.forwarded == 2
    np.testing.assert_array_equal(d[0], d[1])
    np.testing.assert_array_equal(d[0], d[2])


def test_extractor_version_is_part_of_the_key(images, cache):
    extract_descriptors(images, CountingExtractor(), cache=cache)

    class NextVersion(CountingExtractor):
        version = "test2"

    bumped = NextVersion()
    extract_descriptors(images, bumped, cache=cache)
    assert bumped.forwarded == len(images)
    assert cache.stats()["shards"] == 2


def test_progress_counts_hits_at_the_start(images, cache):
    extract_descriptors(images[:4], CountingExtractor(), cache=cache)
    calls: list[tuple[int, int]] = []
    extract_descriptors(
        images, CountingExtractor(), cache=cache, batch_size=3, progress=lambda d, t: calls.append((d, t))
    )
    assert calls[0] == (4, 10)
    assert calls[-1] == (10, 10)
    done = [d for d, _ in calls]
    assert done == sorted(done) and len(calls) == 1 + 2  # 6 misses in batches of 3


# ------------------------------------------------------------------ damaged shards


def truncate_npy(manifest: Path) -> None:
    npy = manifest.with_suffix(".npy")
    npy.write_bytes(npy.read_bytes()[:-100])


def flip_a_byte(manifest: Path) -> None:
    npy = manifest.with_suffix(".npy")
    data = bytearray(npy.read_bytes())
    data[-7] ^= 0x40  # inside the vectors, past the header: the file still loads
    npy.write_bytes(bytes(data))


def garbage_manifest(manifest: Path) -> None:
    manifest.write_text("{not json")


def delete_npy(manifest: Path) -> None:
    manifest.with_suffix(".npy").unlink()


def wrong_shape_manifest(manifest: Path) -> None:
    content = json.loads(manifest.read_text())
    content["shape"] = [content["shape"][0], content["shape"][1] // 2]
    manifest.write_text(json.dumps(content))


@pytest.mark.parametrize("damage", [truncate_npy, flip_a_byte, garbage_manifest, delete_npy, wrong_shape_manifest])
def test_damaged_shard_is_reported_deleted_and_recomputed(images, cache, damage):
    extractor = CountingExtractor()
    extract_descriptors(images, extractor, cache=cache)
    manifest = only_shard(cache, extractor.cache_key)
    damage(manifest)

    counting = CountingExtractor()
    with pytest.warns(DescriptorCacheWarning, match=manifest.name):
        d = extract_descriptors(images, counting, cache=cache)
    assert counting.forwarded == len(images)
    np.testing.assert_array_equal(d, fresh(images))
    assert not manifest.exists() and not manifest.with_suffix(".npy").exists()
    # the recomputed vectors were written anew and are trusted next time
    assert cache.stats()["shards"] == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = CountingExtractor()
        np.testing.assert_array_equal(extract_descriptors(images, again, cache=cache), d)
    assert again.forwarded == 0


def test_damaged_shard_does_not_hide_a_healthy_copy(images, cache):
    vectors = fresh(images[:2])
    hashes = [DescriptorCache.hash_file(p) for p in images[:2]]
    bad = cache.store("k-1", hashes, vectors)
    good = cache.store("k-1", hashes, vectors)
    flip_a_byte(min(bad, good))  # the one read first
    with pytest.warns(DescriptorCacheWarning):
        index, found = cache.lookup("k-1", hashes)
    np.testing.assert_array_equal(index, [0, 1])
    np.testing.assert_array_equal(found, vectors)


def test_shard_of_another_dimension_is_not_trusted(images, cache):
    hashes = [DescriptorCache.hash_file(p) for p in images[:2]]
    cache.store("k-1", hashes, np.ones((2, 3), dtype=np.float32))
    with pytest.warns(DescriptorCacheWarning, match="3-d, expected 5-d"):
        index, found = cache.lookup("k-1", hashes, dim=5)
    assert len(index) == 0 and found.shape == (0, 5)


# ------------------------------------------------------------------ failed runs keep only checked vectors


def test_unreadable_image_fails_naming_it_and_keeps_the_finished_batches(images, cache, tmp_path):
    extract_descriptors(images[:3], CountingExtractor(), cache=cache)
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8\xff\xe0 this is not really a JPEG")
    # Batches of 4 over 7 misses then the broken file: [3 4 5 6] [7 8 9 broken].
    with pytest.raises(VPRInputError, match=r"broken\.jpg: cannot read the image .*replace or remove the file"):
        extract_descriptors([*images, broken], CountingExtractor(), cache=cache, batch_size=4)
    assert cache.stats()["vectors"] == 3 + 4  # the batch holding the broken image is not kept
    again = CountingExtractor()
    np.testing.assert_array_equal(extract_descriptors(images, again, cache=cache), fresh(images))
    assert sorted(again.loaded) == images[7:]


def test_failure_after_several_shards_keeps_them_and_the_rerun_computes_the_rest(images, cache, tmp_path,
                                                                                  monkeypatch):
    # Shards of 2 images, batches of 2, the broken image in the fifth batch: four shards
    # are written before the failure, and the rerun computes only images 8 and 9.
    import vpr_explorer.descriptors.extract as extract

    monkeypatch.setattr(extract, "SHARD_SIZE", 2)
    broken = tmp_path / "zz_broken.png"
    broken.write_bytes(b"not a png at all")
    with pytest.raises(VPRInputError, match=r"zz_broken\.png"):
        extract_descriptors([*images[:9], broken, images[9]], CountingExtractor(), cache=cache, batch_size=2)
    assert cache.stats()["shards"] == 4 and cache.stats()["vectors"] == 8
    again = CountingExtractor()
    np.testing.assert_array_equal(extract_descriptors(images, again, cache=cache, batch_size=2), fresh(images))
    assert sorted(again.loaded) == images[8:]
    assert cache.stats()["shards"] == 5 and cache.stats()["vectors"] == 10


def test_truncated_jpeg_is_named(images, cache, tmp_path):
    good = tmp_path / "good.jpg"
    Image.open(images[0]).convert("RGB").save(good, quality=90)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(VPRInputError, match=r"cut\.jpg: cannot read the image"):
        extract_descriptors([good, cut], CountingExtractor(), cache=cache)
    assert cache.stats()["shards"] == 0


def test_zero_descriptor_fails_naming_the_image_and_caches_nothing(images, cache, tmp_path):
    blank = tmp_path / "blank.png"
    Image.new("RGB", (96, 48), (40, 40, 40)).save(blank)  # every patch flat -> all zeros
    named = r"1 image\(s\) .*blank\.png.*remove the image or choose another descriptor"
    with pytest.raises(VPRInputError, match=named):
        extract_descriptors([*images, blank], CountingExtractor(), cache=cache)
    assert cache.stats() == {"shards": 0, "vectors": 0, "bytes": 0}


def test_missing_image_is_named(images, cache, tmp_path):
    with pytest.raises(VPRInputError, match=r"nowhere\.png: the image file does not exist"):
        extract_descriptors([images[0], tmp_path / "nowhere.png"], CountingExtractor(), cache=cache)


# ------------------------------------------------------------------ the cache API itself


def test_lookup_partial_and_repeated_hashes(cache):
    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(3, 4)).astype(np.float32)
    hashes = [hashlib.sha256(bytes([i])).hexdigest() for i in range(4)]
    cache.store("k-1", hashes[:3], vectors)
    index, found = cache.lookup("k-1", [hashes[1], hashes[3], hashes[0], hashes[1]])
    np.testing.assert_array_equal(index, [0, 2, 3])
    np.testing.assert_array_equal(found, vectors[[1, 0, 1]])
    assert found.dtype == np.float32


def test_float16_storage_is_close_and_unit_norm(images, tmp_path):
    cache = DescriptorCache(tmp_path / "c16", dtype="float16")
    a = extract_descriptors(images, CountingExtractor(), cache=cache)
    manifest = only_shard(cache, CountingExtractor.name + "-test")
    assert np.load(manifest.with_suffix(".npy")).dtype == np.float16
    b = extract_descriptors(images, CountingExtractor(), cache=cache)
    assert b.dtype == np.float32
    np.testing.assert_allclose(b, a, atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-6)


def fake_hashes(n: int, salt: str = "") -> list[str]:
    """Valid sha256 hex digests standing for ``n`` images."""
    return [hashlib.sha256(f"{salt}{i}".encode()).hexdigest() for i in range(n)]


def unit_rows(n: int, dim: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).standard_normal((n, dim), dtype=np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_lookup_as_float16_from_a_float16_shard_is_the_stored_values(tmp_path):
    cache = DescriptorCache(tmp_path / "c16", dtype="float16")
    vectors = unit_rows(6, 40)
    hashes = fake_hashes(6)
    cache.store("k-1", hashes, vectors)
    stored = np.load(only_shard(cache, "k-1").with_suffix(".npy"))
    assert stored.dtype == np.float16
    index, found = cache.lookup("k-1", hashes, 40, dtype="float16")
    np.testing.assert_array_equal(index, np.arange(6))
    assert found.dtype == np.float16 and found.shape == (6, 40)
    np.testing.assert_array_equal(found, stored)
    # the float32 default gives the same values, widened exactly
    index, wide = cache.lookup("k-1", hashes, 40)
    assert wide.dtype == np.float32
    np.testing.assert_array_equal(wide, stored.astype(np.float32))


def test_lookup_as_float16_from_a_float32_shard_rounds_the_stored_values(cache):
    vectors = unit_rows(6, 40)
    hashes = fake_hashes(6)
    cache.store("k-1", hashes, vectors)
    index, found = cache.lookup("k-1", hashes[::-1], 40, dtype=np.float16)
    np.testing.assert_array_equal(index, np.arange(6))
    assert found.dtype == np.float16
    np.testing.assert_array_equal(found, vectors[::-1].astype(np.float16))
    assert not np.array_equal(found.astype(np.float32), vectors[::-1])  # really rounded


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_lookup_across_shards_with_misses_and_repeats(tmp_path, monkeypatch, dtype):
    # One-row gathers: every slice boundary of the gather and of the compaction is crossed.
    import vpr_explorer.descriptors.cache as cache_module

    monkeypatch.setattr(cache_module, "GATHER_BYTES", 1)
    cache = DescriptorCache(tmp_path / "c", dtype="float16")
    truth = {}
    for s in range(3):
        hashes, vectors = fake_hashes(5, f"shard{s}-"), unit_rows(5, 8, seed=s)
        cache.store("k-1", hashes, vectors)
        truth.update(zip(hashes, vectors.astype(np.float16)))
    cached = list(truth)
    missing = fake_hashes(4, "missing-")
    asked = [missing[0], cached[7], cached[0], missing[1], cached[14], cached[7], missing[2], cached[3],
             missing[3], cached[11]]
    index, found = cache.lookup("k-1", asked, 8, dtype=dtype)
    np.testing.assert_array_equal(index, [1, 2, 4, 5, 7, 9])
    assert found.dtype == dtype and found.shape == (6, 8) and found.flags.owndata
    np.testing.assert_array_equal(found, np.stack([truth[asked[i]] for i in index]).astype(dtype))
    index, found = cache.lookup("k-1", missing, 8, dtype=dtype)
    assert len(index) == 0 and found.shape == (0, 8) and found.dtype == dtype


def check_float16_result(got: np.ndarray, reference: np.ndarray) -> None:
    """A float16 result: right dtype and shape, close to the float32 reference, unit rows to float16 precision."""
    assert got.dtype == np.float16 and got.shape == reference.shape
    assert not got.flags.writeable
    np.testing.assert_allclose(got.astype(np.float32), reference, atol=1e-3, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(got.astype(np.float32), axis=1), 1.0, atol=2e-3)


@pytest.mark.parametrize("storage", ["float16", "float32"])
def test_float16_results_cold_warm_and_partly_warm(images, tmp_path, storage):
    reference = fresh(images)
    cache = DescriptorCache(tmp_path / storage, dtype=storage)
    # Partly warm: four images cached first, the other six computed into the float16 result.
    extract_descriptors(images[:4], CountingExtractor(), cache=cache)
    counting = CountingExtractor()
    partly = extract_descriptors(images, counting, cache=cache, dtype="float16")
    assert counting.forwarded == 6
    check_float16_result(partly, reference)
    for shard in (cache.folder / CountingExtractor().cache_key).glob("*.npy"):
        assert np.load(shard).dtype == storage  # the cache's storage dtype decides, not the result's

    cold = extract_descriptors(images, CountingExtractor(), cache=DescriptorCache(tmp_path / "other", dtype=storage),
                               dtype="float16")
    check_float16_result(cold, reference)
    np.testing.assert_array_equal(cold, reference.astype(np.float16))
    np.testing.assert_array_equal(partly, cold)

    warm_counting = CountingExtractor()
    warm = extract_descriptors([*images, images[3]], warm_counting, cache=cache, dtype="float16")
    assert warm_counting.forwarded == 0 and warm_counting.loaded == []
    check_float16_result(warm[:-1], reference)
    np.testing.assert_array_equal(warm[:-1], cold)  # a cached float16 run equals the run that filled it
    np.testing.assert_array_equal(warm[-1], cold[3])

    warm32 = extract_descriptors(images, CountingExtractor(), cache=cache)
    assert warm32.dtype == np.float32
    if storage == "float32":
        np.testing.assert_array_equal(warm32, reference)  # still bit-identical
    else:
        np.testing.assert_allclose(warm32, reference, atol=1e-3)
        np.testing.assert_allclose(np.linalg.norm(warm32, axis=1), 1.0, atol=1e-6)


def test_bad_result_dtype_is_named_before_any_work(images, cache):
    counting = CountingExtractor()
    named = r"dtype='float64' is not a descriptor dtype: choose one of float32, float16"
    with pytest.raises(VPRInputError, match=named):
        extract_descriptors(images, counting, cache=cache, dtype="float64")
    assert counting.loaded == [] and cache.stats()["shards"] == 0


def traced_peak(work) -> tuple[int, object]:
    """Peak bytes traced (numpy reports its buffers to tracemalloc) while ``work()`` runs, and its result."""
    tracemalloc.start()
    try:
        result = work()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return peak, result


def test_float16_lookup_holds_no_float32_copy(tmp_path):
    n, dim = 8192, 1280  # two shards of 1280-d vectors (the size of EfficientNet-Lite0's)
    cache = DescriptorCache(tmp_path / "c", dtype="float16")
    hashes = fake_hashes(n)
    vectors = unit_rows(n, dim)
    for lo in range(0, n, 4096):  # extract_descriptors' SHARD_SIZE
        cache.store("k-1", hashes[lo : lo + 4096], vectors[lo : lo + 4096])
    del vectors
    result_bytes = n * dim * 2

    def half() -> np.ndarray:
        return cache.lookup("k-1", hashes, dim, dtype="float16").vectors  # extract_descriptors does no more

    def single() -> np.ndarray:
        found = cache.lookup("k-1", hashes, dim).vectors
        renormalise_in_place(found)  # what extract_descriptors does to float32 hits
        return found

    peak16, got16 = traced_peak(half)
    assert got16.dtype == np.float16 and got16.shape == (n, dim)
    assert peak16 < 1.3 * result_bytes, f"peak {peak16 / 1e6:.1f} MB for a {result_bytes / 1e6:.1f} MB result"
    del got16
    peak32, got32 = traced_peak(single)
    np.testing.assert_allclose(np.linalg.norm(got32, axis=1), 1.0, atol=1e-6)  # renormalised
    assert peak32 < 1.3 * 2 * result_bytes  # the float32 result, no full-size temporaries
    assert 1.6 < peak32 / peak16 < 2.4


class NeverComputes(Extractor):
    """A wide descriptor that is only ever read from the cache."""

    name, version, dim = "wide", "test", 4096

    def load(self, path: Path) -> np.ndarray:
        raise AssertionError(f"{path} was decoded although it is cached")

    def forward(self, batch: np.ndarray) -> np.ndarray:
        raise AssertionError("a batch was forwarded although every image is cached")


def test_warm_float16_extraction_holds_no_float32_copy(tmp_path):
    n = 2000
    folder = tmp_path / "files"
    folder.mkdir()
    paths = []
    for i in range(n):  # never decoded: only their bytes (hash) matter
        path = folder / f"{i:05d}.png"
        path.write_bytes(str(i).encode())
        paths.append(path)
    cache = DescriptorCache(tmp_path / "c", dtype="float16")
    extractor = NeverComputes()
    cache.store(extractor.cache_key, [hashlib.sha256(str(i).encode()).hexdigest() for i in range(n)],
                unit_rows(n, extractor.dim))
    result_bytes = n * extractor.dim * 2

    peak16, got16 = traced_peak(lambda: extract_descriptors(paths, extractor, cache=cache, dtype="float16"))
    assert got16.dtype == np.float16 and got16.shape == (n, extractor.dim)
    assert peak16 < 1.3 * result_bytes, f"peak {peak16 / 1e6:.1f} MB for a {result_bytes / 1e6:.1f} MB result"
    peak32, got32 = traced_peak(lambda: extract_descriptors(paths, extractor, cache=cache))
    np.testing.assert_allclose(got32, got16.astype(np.float32), atol=1e-3)
    assert 1.6 < peak32 / peak16 < 2.4


def test_bad_arguments_raise_input_errors(cache, tmp_path):
    with pytest.raises(VPRInputError, match="dtype="):
        DescriptorCache(tmp_path, dtype="int8")
    for bad in ("int8", "float64", "half-precision"):
        named = rf"dtype={bad!r} is not a descriptor dtype: choose one of float32, float16"
        with pytest.raises(VPRInputError, match=named):
            cache.lookup("k-1", [], dtype=bad)
    with pytest.raises(VPRInputError, match="cache_key="):
        cache.lookup("../escape", [])
    h = hashlib.sha256(b"x").hexdigest()
    with pytest.raises(VPRInputError, match="vectors: shape"):
        cache.store("k-1", [h], np.zeros((2, 3), dtype=np.float32))
    with pytest.raises(VPRInputError, match="NaN"):
        cache.store("k-1", [h], np.full((1, 3), np.nan, dtype=np.float32))
    with pytest.raises(VPRInputError, match="not a sha256"):
        cache.store("k-1", ["abc"], np.zeros((1, 3), dtype=np.float32))
    assert cache.stats()["shards"] == 0


def test_hash_file_is_sha256_of_the_bytes_and_names_missing_files(images, tmp_path):
    assert DescriptorCache.hash_file(images[0]) == hashlib.sha256(images[0].read_bytes()).hexdigest()
    with pytest.raises(VPRInputError, match=r"gone\.png: the image file does not exist"):
        DescriptorCache.hash_file(tmp_path / "gone.png")


def test_default_root_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("VPR_EXPLORER_CACHE", str(tmp_path / "env-cache"))
    assert DescriptorCache().root == tmp_path / "env-cache"
    assert DescriptorCache().folder == tmp_path / "env-cache" / "descriptors"


def test_clear_and_stats(images, cache):
    extract_descriptors(images, CountingExtractor(), cache=cache)
    hashes = [DescriptorCache.hash_file(p) for p in images[:2]]
    cache.store("other-1", hashes, np.ones((2, 5), dtype=np.float32))
    stats = cache.stats()
    assert stats["shards"] == 2 and stats["vectors"] == len(images) + 2
    npy_bytes = sum(p.stat().st_size for p in cache.folder.rglob("*.npy"))
    assert stats["bytes"] > npy_bytes
    assert cache.stats("other-1")["vectors"] == 2

    cache.clear("other-1")
    assert cache.stats() == cache.stats("counting-pixels-test") and cache.stats()["shards"] == 1
    keep = cache.folder / "counting-pixels-test" / "notes.txt"
    keep.write_text("not the cache's")
    cache.clear()
    assert cache.stats() == {"shards": 0, "vectors": 0, "bytes": 0}
    assert keep.read_text() == "not the cache's"


def test_concurrent_readers_never_see_a_partial_shard(cache):
    """Readers racing a writer only ever see whole shards: no warnings, consistent rows."""
    rng = np.random.default_rng(1)
    dim, per_shard, n_shards = 64, 50, 12
    shards = []
    for s in range(n_shards):
        hashes = [hashlib.sha256(f"{s}-{i}".encode()).hexdigest() for i in range(per_shard)]
        shards.append((hashes, rng.normal(size=(per_shard, dim)).astype(np.float32)))
    truth = {h: v for hashes, vectors in shards for h, v in zip(hashes, vectors)}
    all_hashes = list(truth)
    failures: list[str] = []
    stop = threading.Event()

    def reader() -> None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            while not stop.is_set():
                index, found = cache.lookup("race-1", all_hashes, dim)
                if len(index) % per_shard:
                    failures.append(f"saw {len(index)} rows, not whole shards")
                for i, v in zip(index, found):
                    if not np.array_equal(truth[all_hashes[i]], v):
                        failures.append("a row differs from what was written")
                        break
        failures.extend(str(w.message) for w in caught)

    threads = [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    for hashes, vectors in shards:
        cache.store("race-1", hashes, vectors)
    stop.set()
    for t in threads:
        t.join()
    assert failures == []
    index, found = cache.lookup("race-1", all_hashes, dim)
    assert len(index) == len(all_hashes)


def test_an_exact_cache_never_serves_float16_vectors_a_float16_cache_reads_both(tmp_path):
    """After a float16 run, a float32 cache counts those images as misses (recomputed, exact)."""
    rng = np.random.default_rng(5)
    vectors = rng.standard_normal((4, 16)).astype(np.float32)
    hashes = [hashlib.sha256(str(i).encode()).hexdigest() for i in range(4)]
    DescriptorCache(tmp_path, dtype="float16").store("k", hashes[:2], vectors[:2])
    DescriptorCache(tmp_path, dtype="float32").store("k", hashes[2:], vectors[2:])
    exact = DescriptorCache(tmp_path, dtype="float32").lookup("k", hashes, 16)
    np.testing.assert_array_equal(exact.index, [2, 3])
    np.testing.assert_array_equal(exact.vectors, vectors[2:])
    half = DescriptorCache(tmp_path, dtype="float16").lookup("k", hashes, 16, dtype="float16")
    np.testing.assert_array_equal(half.index, [0, 1, 2, 3])
    np.testing.assert_array_equal(half.vectors, vectors.astype(np.float16))
