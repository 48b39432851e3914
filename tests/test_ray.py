"""Extraction on Ray (``vpr-explorer extract --ray``): the local extractor's vectors, in the same cache.

One local Ray instance of this machine (2 CPUs, a small object store, no dashboard)
serves every test; the jobs run in this process (``extract_on_ray``) and as real
``vpr-explorer extract --ray ADDRESS`` processes, the command the README gives. The
images are 40 real GardensPoint frames (``day_left`` and ``night_right``, frames
170-189), among them night_right's byte-identical 179 and 183, so 39 distinct contents.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import ray  # in the test extra, so these tests run wherever the others do

from vpr_explorer.cli import main
from vpr_explorer.descriptors import DescriptorCache, DescriptorCacheWarning, extract_descriptors, get_extractor
from vpr_explorer.descriptors.cache import hash_file

pytestmark = pytest.mark.realdata

FRAMES = range(170, 190)
TRAVERSALS = ("day_left", "night_right")
N_IMAGES = len(FRAMES) * len(TRAVERSALS)
N_DISTINCT = N_IMAGES - 1  # night_right/Image179.jpg == Image183.jpg
# Ray runs the local extractor's own load, forward and normalisation: pixels is the same
# float32 arithmetic (bit-equal); a torch model's vectors differ by the rounding of other
# batch splits (batch 4 against 32 here) and thread counts: measured 2e-7 on unit vectors.
BOUND = {"pixels": 1e-6, "efficientnet-lite0": 1e-5}
FINAL = re.compile(r"^(\d+) images: (\d+) already cached, (\d+) computed on Ray")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cluster():
    """The GCS address of a local Ray instance, 2 CPUs; shut down after the module.

    Its workers run at the tests' priority (Ray's default niceness, 15, lets any busy
    process on the machine starve them).
    """
    if ray.is_initialized():
        ray.shutdown()
    old = os.environ.get("RAY_worker_niceness")
    os.environ["RAY_worker_niceness"] = "0"
    try:
        context = ray.init(address="local", num_cpus=2, object_store_memory=100 * 2**20, include_dashboard=False,
                           log_to_driver=False)
        yield context.address_info["gcs_address"]
    finally:
        ray.shutdown()
        if old is None:
            os.environ.pop("RAY_worker_niceness", None)
        else:
            os.environ["RAY_worker_niceness"] = old


@pytest.fixture(scope="module")
def subset(data_root, tmp_path_factory) -> Path:
    """40 GardensPoint frames, copied byte for byte (so their content keys are GardensPoint's)."""
    root = tmp_path_factory.mktemp("gp40")
    for traversal in TRAVERSALS:
        (root / traversal).mkdir()
        for frame in FRAMES:
            name = f"Image{frame:03d}.jpg"
            shutil.copyfile(data_root / "GardensPointWalking" / traversal / name, root / traversal / name)
    return root


@pytest.fixture(scope="module")
def paths(subset) -> list[Path]:
    from vpr_explorer.data.traversals import load_dataset

    return list(load_dataset(subset).image_paths)


@pytest.fixture(scope="module")
def reference(paths, tmp_path_factory):
    """The local extractor's vectors of the subset, per descriptor (a cache of their own)."""
    root = tmp_path_factory.mktemp("local_cache")
    return {name: extract_descriptors(paths, get_extractor(name), cache=DescriptorCache(root))
            for name in BOUND}


def read_back(paths, name, root) -> tuple[int, np.ndarray]:
    """``(images found cached, vectors)`` of a local run on cache ``root``; a damaged shard fails the test."""
    hits = []
    with warnings.catch_warnings():
        warnings.simplefilter("error", DescriptorCacheWarning)
        out = extract_descriptors(paths, get_extractor(name), cache=DescriptorCache(root),
                                  progress=lambda done, total: hits.append(done))
    return hits[0], out


def cli(subset, cache, address, *extra) -> list[str]:
    return [sys.executable, "-m", "vpr_explorer.cli", "extract", "--dataset", str(subset), "--cache-dir", str(cache),
            "--ray", address, *extra]


def shards_of(cache: Path, name: str) -> dict[str, list[str]]:
    """Manifest file name -> the hashes it lists, for ``name``'s key."""
    import json

    folder = DescriptorCache(cache).folder / get_extractor(name).cache_key
    return {p.name: json.loads(p.read_text())["hashes"] for p in sorted(folder.glob("*.json"))}


# ------------------------------------------------------------------ the local extractor's vectors


@pytest.mark.parametrize("name", list(BOUND))
def test_ray_fills_the_cache_with_the_local_extractors_vectors(cluster, paths, reference, name, tmp_path):
    from vpr_explorer.descriptors.distributed import extract_on_ray

    seen = []
    job = extract_on_ray(paths, name, cache_root=tmp_path, batch_size=8, shard_images=16,
                         progress=lambda done, total: seen.append((done, total)))
    assert (job.total, job.cached, job.computed) == (N_IMAGES, 0, N_DISTINCT)
    assert (job.actors, job.cpus, job.gpus) == (1, 2.0, False)  # one actor holding both CPUs of the node
    assert seen[0] == (0, N_IMAGES) and seen[-1] == (N_IMAGES, N_IMAGES)
    assert sum(len(h) for h in shards_of(tmp_path, name).values()) == N_DISTINCT  # each content once
    cached, out = read_back(paths, name, tmp_path)
    assert cached == N_IMAGES  # a local run afterwards finds everything cached
    delta = float(np.abs(out - reference[name]).max())
    assert delta < BOUND[name], f"{name}: max |Δ| {delta:.2e} against the local extractor"
    # a second job finds everything and computes nothing
    again = extract_on_ray(paths, name, cache_root=tmp_path)
    assert (again.cached, again.computed) == (N_IMAGES, 0)


# ------------------------------------------------------------------ killed midway, then resumed


def test_a_killed_job_resumes_and_computes_only_what_is_missing(cluster, subset, paths, reference, tmp_path):
    name = "efficientnet-lite0"
    cache = tmp_path / "cache"
    command = cli(subset, cache, cluster, "--descriptor", name, "--batch-size", "2", "--shard-images", "2")
    job = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.monotonic() + 120
    while len(shards_of(cache, name)) < 3 and job.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert job.poll() is None, f"the job ended before it could be killed: {job.communicate()}"
    job.send_signal(signal.SIGKILL)
    job.communicate()
    # Its actors die with its driver; wait until no shard has come for 3 s.
    last, since = shards_of(cache, name), time.monotonic()
    while time.monotonic() - since < 3 and time.monotonic() < deadline:
        time.sleep(0.2)
        now = shards_of(cache, name)
        if now != last:
            last, since = now, time.monotonic()
    before = {h for hashes in last.values() for h in hashes}
    assert 3 <= len(before) < N_DISTINCT, f"{len(before)} of {N_DISTINCT} cached when killed"
    cached_images = sum(hash_file(p) in before for p in paths)

    # The same job again (here in this process, on the same cluster).
    from vpr_explorer.descriptors.distributed import extract_on_ray

    resumed = extract_on_ray(paths, name, cache_root=cache, batch_size=8, shard_images=8)
    assert (resumed.total, resumed.cached) == (N_IMAGES, cached_images)
    assert resumed.computed == N_DISTINCT - len(before)
    # Count what the resumed job computed from the cache itself: the shards it added hold
    # exactly the contents that were missing, each once.
    added = [h for shard, hashes in shards_of(cache, name).items() if shard not in last for h in hashes]
    assert len(added) == len(set(added)) == N_DISTINCT - len(before)
    assert not set(added) & before
    cached, out = read_back(paths, name, cache)
    assert cached == N_IMAGES
    assert float(np.abs(out - reference[name]).max()) < BOUND[name]


# ------------------------------------------------------------------ two jobs, one cache


def test_two_jobs_on_one_cache_at_once_leave_it_whole(cluster, subset, paths, reference, tmp_path):
    name = "pixels"
    cache = tmp_path / "cache"
    command = cli(subset, cache, cluster, "--descriptor", name, "--batch-size", "2", "--shard-images", "4")
    jobs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
            for _ in range(2)]
    results = [job.communicate(timeout=120) for job in jobs]
    for job, (out, err) in zip(jobs, results):
        assert job.returncode == 0, err[-2000:]
        assert FINAL.match(out.strip().splitlines()[-1]), out
    hashes = [h for shard in shards_of(cache, name).values() for h in shard]
    assert set(hashes) == {hash_file(p) for p in paths}  # every content, from one job or the other
    cached, out = read_back(paths, name, cache)  # every shard's checksum verified, none damaged
    assert cached == N_IMAGES
    assert float(np.abs(out - reference[name]).max()) < BOUND[name]
    folder = DescriptorCache(cache).folder
    leftovers = [p.name for p in [*folder.iterdir(), *(folder / get_extractor(name).cache_key).iterdir()]
                 if p.name.startswith(".")]
    assert leftovers == []  # no temporaries, no probe file


# ------------------------------------------------------------------ the actor pool for a cluster


def test_the_actor_pool_is_sized_to_the_clusters_nodes():
    from vpr_explorer.descriptors.distributed import _pool_shape
    from vpr_explorer.errors import VPRInputError

    def shape(nodes, actors=None, threads=None):
        pool = _pool_shape(nodes, actors, threads)
        return pool.actors, pool.cpus, pool.gpus, pool.threads

    assert shape([{"CPU": 2.0}]) == (1, 2.0, False, 2)  # this machine: one actor on both CPUs
    assert shape([{"CPU": 16.0}] * 3) == (3, 16.0, False, 16)  # one per node, each on its cores
    assert shape([{"CPU": 2.0}, {"CPU": 8.0}]) == (5, 2.0, False, 2)  # the smallest node's size: 1 + 4
    assert shape([{"CPU": 0.0}, {"CPU": 4.0}]) == (1, 4.0, False, 4)  # a head without CPUs holds none
    assert shape([{"CPU": 2.0}], actors=2) == (2, 1.0, False, 1)
    assert shape([{"CPU": 3.0}, {"CPU": 3.0}], actors=3) == (3, 1.0, False, 1)  # 2 CPUs each would fit only 2
    assert shape([{"CPU": 2.0}], actors=3) == (3, 0.66, False, 1)
    assert shape([{"CPU": 2.0}], threads=4) == (1, 2.0, False, 4)
    # one actor per GPU, with its share of the leanest GPU node's CPUs for decoding
    assert shape([{"CPU": 16.0, "GPU": 2.0}, {"CPU": 6.0, "GPU": 1.0}, {"CPU": 8.0}]) == (3, 6.0, True, 6)
    assert shape([{"CPU": 16.0, "GPU": 4.0}], actors=2) == (2, 4.0, True, 4)
    assert shape([{"CPU": 16.0, "GPU": 1.0}], actors=3) == (1, 16.0, True, 16)  # no more than the GPUs
    for bad in ({"actors": 0}, {"actors": True}, {"threads": 1.5}):
        with pytest.raises(VPRInputError, match="must be a whole number"):
            _pool_shape([{"CPU": 2.0}], **bad)
    with pytest.raises(VPRInputError, match="no node with CPUs or GPUs"):
        _pool_shape([{"CPU": 0.0}])


# ------------------------------------------------------------------ errors and the optional import


def test_an_unreadable_image_is_named_in_one_line(cluster, subset, tmp_path):
    from vpr_explorer.descriptors.distributed import extract_on_ray
    from vpr_explorer.errors import VPRInputError

    data = (subset / "day_left" / "Image170.jpg").read_bytes()
    bad = tmp_path / "truncated.jpg"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(VPRInputError) as raised:
        extract_on_ray([subset / "day_left" / "Image171.jpg", bad], "pixels", cache_root=tmp_path / "cache")
    message = str(raised.value)
    assert message.startswith(f"{bad}: cannot read the image") and "\n" not in message  # the worker's error, unwrapped


def test_the_command_line_never_imports_ray_unless_asked():
    code = ("import sys; from vpr_explorer.cli.parser import build_parser; build_parser(); "
            "print('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"


def test_without_ray_the_command_says_how_to_install_it(subset, tmp_path):
    # ray made unimportable in a fresh interpreter, as where the extra is not installed
    code = ("import sys; sys.modules['ray'] = None; from vpr_explorer.cli import main; "
            f"sys.exit(main(['extract', '--dataset', {str(subset)!r}, '--descriptor', 'pixels', "
            f"'--cache-dir', {str(tmp_path)!r}, '--ray', 'local']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and 'pip install ".[ray]"' in lines[0]


def test_an_unreachable_address_is_one_error_line(subset, tmp_path, capsys):
    with socket_listening_nowhere() as address:
        assert main(["extract", "--dataset", str(subset), "--descriptor", "pixels", "--cache-dir", str(tmp_path),
                     "--ray", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unreachable" in err[0] and address in err[0]
    assert main(["extract", "--dataset", str(subset), "--descriptor", "pixels", "--ray", "nonsense"]) == 2
    assert "HOST:PORT" in capsys.readouterr().err


def test_local_extraction_prints_images_per_second_and_cached(subset, tmp_path, capsys):
    args = ["extract", "--dataset", str(subset), "--descriptor", "pixels", "--cache-dir", str(tmp_path)]
    assert main(args) == 0
    assert re.match(rf"^{N_IMAGES} images: 0 already cached, {N_IMAGES} computed locally in [\d.]+ s, [\d.]+ images/s$",
                    capsys.readouterr().out.strip())
    assert main(args) == 0
    assert capsys.readouterr().out.startswith(f"{N_IMAGES} images: {N_IMAGES} already cached, 0 computed")
    assert main([*args, "--actors", "2"]) == 2  # a Ray option without --ray
    assert "--ray" in capsys.readouterr().err


class socket_listening_nowhere:
    """``127.0.0.1:PORT`` of a port just closed: connections are refused."""

    def __enter__(self) -> str:
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        return f"127.0.0.1:{port}"

    def __exit__(self, *exc) -> None:
        return None
