"""The on-disk descriptor cache: hits, content keying, damage detection, failed runs, concurrency."""

from __future__ import annotations

import hashlib
import json
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

from images import write_random_png
from PIL import Image

from vpr_explorer.descriptors import DescriptorCache, DescriptorCacheWarning, extract_descriptors
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
    (manifest,) = sorted((cache.root / key).glob("*.json"))
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


# ------------------------------------------------------------------ failed runs write nothing


def test_unreadable_image_fails_naming_it_and_caches_nothing(images, cache, tmp_path):
    extract_descriptors(images[:3], CountingExtractor(), cache=cache)
    before = cache.stats()
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8\xff\xe0 this is not really a JPEG")
    with pytest.raises(VPRInputError, match=r"broken\.jpg: cannot read the image .*replace or remove the file"):
        extract_descriptors([*images, broken], CountingExtractor(), cache=cache, batch_size=4)
    assert cache.stats() == before


def test_failure_after_several_shards_worth_caches_nothing(images, cache, tmp_path, monkeypatch):
    # With shards of 2 images, batches of 2 and the broken image last, four full shards'
    # worth of vectors pass their checks before the failure: none of them may be kept.
    import vpr_explorer.descriptors.extract as extract

    monkeypatch.setattr(extract, "SHARD_SIZE", 2)
    broken = tmp_path / "zz_broken.png"
    broken.write_bytes(b"not a png at all")
    with pytest.raises(VPRInputError, match=r"zz_broken\.png"):
        extract_descriptors([*images, broken], CountingExtractor(), cache=cache, batch_size=2)
    assert cache.stats() == {"shards": 0, "vectors": 0, "bytes": 0}
    extract_descriptors(images, CountingExtractor(), cache=cache, batch_size=2)
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


def test_bad_arguments_raise_input_errors(cache, tmp_path):
    with pytest.raises(VPRInputError, match="dtype="):
        DescriptorCache(tmp_path, dtype="int8")
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
    assert DescriptorCache().root == tmp_path / "env-cache" / "descriptors"


def test_clear_and_stats(images, cache):
    extract_descriptors(images, CountingExtractor(), cache=cache)
    hashes = [DescriptorCache.hash_file(p) for p in images[:2]]
    cache.store("other-1", hashes, np.ones((2, 5), dtype=np.float32))
    stats = cache.stats()
    assert stats["shards"] == 2 and stats["vectors"] == len(images) + 2
    npy_bytes = sum(p.stat().st_size for p in cache.root.rglob("*.npy"))
    assert stats["bytes"] > npy_bytes
    assert cache.stats("other-1")["vectors"] == 2

    cache.clear("other-1")
    assert cache.stats() == cache.stats("counting-pixels-test") and cache.stats()["shards"] == 1
    keep = cache.root / "counting-pixels-test" / "notes.txt"
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
