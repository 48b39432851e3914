"""Interrupted and killed extractions: finished work is kept and resumed, leftovers are cleaned.

Real processes and real signals: a child extracts GardensPoint with ``pixels`` and is
sent SIGINT midway; another is SIGKILLed while it writes a shard.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from images import write_random_png

from vpr_explorer import settings
from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
from vpr_explorer.descriptors.cache import hash_file
from vpr_explorer.descriptors.pixels import PixelsExtractor

ROOT = Path(__file__).resolve().parents[1]
INTERRUPT_AFTER = 48  # images done before the child is sent SIGINT


class CountingPixels(PixelsExtractor):
    """``pixels`` under its own cache key, recording the images it decoded."""

    def __init__(self) -> None:
        self.loaded: list[Path] = []

    def load(self, path: Path) -> np.ndarray:
        self.loaded.append(Path(path))
        return super().load(path)


#: a child's first lines: Python's own Ctrl-C handler, whatever SIGINT disposition the test process had when it
#: forked. Once, in a full run, a child ran to its end after the test's Ctrl-C (exit 0, nothing on stderr); an
#: ignored SIGINT, which exec keeps (POSIX system() in any thread ignores it for the process meanwhile), is
#: the one cause we know of
DEFAULT_SIGINT = "import signal\nsignal.signal(signal.SIGINT, signal.default_int_handler)\n"


def child(tmp_path: Path, code: str, *args: str) -> subprocess.Popen:
    script = tmp_path / "child.py"
    script.write_text(DEFAULT_SIGINT + textwrap.dedent(code))
    return subprocess.Popen([sys.executable, str(script), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT)


# ------------------------------------------------------------------ written as the run goes


def test_shards_are_written_while_the_run_goes(tmp_path, monkeypatch):
    import vpr_explorer.descriptors.extract as extract

    monkeypatch.setattr(extract, "FLUSH_SECONDS", 0.0)  # every finished batch is due at once
    images = [write_random_png(tmp_path / f"im{i}.png", seed=i, size=(96, 48)) for i in range(10)]
    cache = DescriptorCache(tmp_path / "cache")
    seen: list[int] = []
    folder = cache.folder / PixelsExtractor().cache_key

    def progress(done: int, total: int) -> None:
        seen.append(len(list(folder.glob("*.json"))) if folder.is_dir() else 0)

    extract_descriptors(images, PixelsExtractor(), cache=cache, batch_size=3, progress=progress)
    # progress runs after each batch is stored: 0 before the first, then one shard per batch
    assert seen == [0, 1, 2, 3, 4]


# ------------------------------------------------------------------ Ctrl-C, then resume

EXTRACT_AND_REPORT = """
    import sys
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.descriptors import DescriptorCache, ExtractionInterrupted, extract_descriptors, get_extractor

    dataset = load_dataset(sys.argv[1])

    def progress(done, total):
        print(done, total, flush=True)

    try:
        extract_descriptors(list(dataset.image_paths), get_extractor("pixels"), cache=DescriptorCache(sys.argv[2]),
                            batch_size=8, workers=1, progress=progress)
    except ExtractionInterrupted as exc:  # what the command line does with it
        print(f"interrupted: {exc}", file=sys.stderr)
        sys.exit(130)
"""


@pytest.mark.realdata
def test_ctrl_c_keeps_the_finished_batches_and_the_rerun_computes_only_the_rest(gardens_point, tmp_path):
    paths = list(gardens_point.image_paths)
    root = tmp_path / "cache"
    proc = child(tmp_path, EXTRACT_AND_REPORT, str(gardens_point.root), str(root))
    for line in proc.stdout:
        done, total = map(int, line.split())
        if done >= INTERRUPT_AFTER:
            proc.send_signal(signal.SIGINT)
            break
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    reported = re.fullmatch(r"interrupted: (\d+) of 600 descriptors cached; run the same command again to resume", line)
    assert reported, line
    n_cached = int(reported[1])
    assert INTERRUPT_AFTER <= n_cached < len(paths)

    cache = DescriptorCache(root)
    key = get_extractor("pixels").cache_key
    hashes = [hash_file(p) for p in paths]
    index, _ = cache.lookup(key, hashes, PixelsExtractor.dim)
    assert len(index) == n_cached  # the message tells the truth
    missing = set(hashes) - {hashes[i] for i in index}

    counting, calls = CountingPixels(), []
    resumed = extract_descriptors(paths, counting, cache=cache, progress=lambda d, t: calls.append((d, t)))
    assert calls[0] == (n_cached, len(paths))  # reported as cached up front
    assert sorted(hash_file(p) for p in counting.loaded) == sorted(missing)  # only the missing ones computed
    clean = extract_descriptors(paths, PixelsExtractor())
    assert resumed.tobytes() == clean.tobytes()


# ------------------------------------------------------------------ SIGKILL mid-write

STORE_FOREVER = """
    import sys
    import numpy as np
    from vpr_explorer.descriptors import DescriptorCache

    cache = DescriptorCache(sys.argv[1])
    rows = np.ones((2048, 2048), dtype=np.float32)
    hashes = [f"{i:064x}" for i in range(len(rows))]
    while True:
        manifest = cache.store(sys.argv[2], hashes, rows)
        manifest.unlink()  # keep the disk use to one shard
        manifest.with_suffix(".npy").unlink()
"""


def kill_mid_write(tmp_path: Path, root: Path, key: str) -> Path:
    """SIGKILL a process while it writes a shard temporary; the temporary it leaves."""
    folder = DescriptorCache(root).folder / key
    for _attempt in range(20):
        proc = child(tmp_path, STORE_FOREVER, str(root), key)
        deadline = time.monotonic() + 30
        left = []
        while time.monotonic() < deadline and proc.poll() is None:
            temporaries = [p for p in folder.glob(".*.tmp")] if folder.is_dir() else []
            if temporaries:
                proc.kill()
                proc.wait()
                left = [p for p in temporaries if p.exists()]
                break
            time.sleep(0.0005)
        else:
            proc.kill()
            proc.wait()
            pytest.fail(f"the writer never wrote a temporary: {proc.stderr.read()}")
        if left:
            (leftover,) = left
            assert settings.temporary_owner(leftover.name)[1] == proc.pid
            return leftover
    pytest.fail("never caught the writer mid-write in 20 tries")


def age(path: Path, seconds: float) -> None:
    then = time.time() - seconds
    os.utime(path, (then, then))


def test_leftovers_of_killed_writers_are_removed_and_live_writers_files_kept(tmp_path):
    root = tmp_path / "cache"
    key = PixelsExtractor().cache_key
    killed = kill_mid_write(tmp_path, root, key)
    cache = DescriptorCache(root)
    folder = cache.folder / key
    host = settings.host_tag()

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    orphan = folder / f"{'a' * 32}.{host}.{dead_pid}.npy"  # its manifest never came
    live = folder / settings.temporary_name("b.npy")  # this process: a live writer
    other_host = folder / f".c.npy.elsewhere.{os.getpid()}.{'c' * 32}.tmp"
    old_style_recent = folder / f".d.npy.{'d' * 32}.tmp"
    old_style_old = folder / f".e.npy.{'e' * 32}.tmp"
    user_file = folder / "notes.txt"
    for path in (orphan, live, other_host, old_style_recent, old_style_old, user_file):
        path.write_bytes(b"x")
    age(live, 10 * 3600)
    age(other_host, 600)
    age(old_style_old, 2 * 3600)
    age(orphan, 120)

    # The killed writer's temporary is kept for a minute (another pid namespace may share
    # this host name), then removed.
    assert cache.remove_stale(key) == 2  # orphan, old_style_old
    assert killed.exists()
    age(killed, 120)
    images = [write_random_png(tmp_path / f"im{i}.png", seed=i, size=(96, 48)) for i in range(3)]
    extract_descriptors(images, PixelsExtractor(), cache=cache)  # cleans before it starts
    assert not killed.exists() and not orphan.exists() and not old_style_old.exists()
    assert live.exists() and other_host.exists() and old_style_recent.exists() and user_file.exists()
    assert cache.stats(key)["vectors"] == 3
    assert sorted(p.name for p in folder.glob(".*.tmp")) == sorted(
        p.name for p in (live, other_host, old_style_recent))
