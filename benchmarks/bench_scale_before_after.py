"""The 50-split protocol's pass and whole run: an earlier commit's one-file ``scale`` against the package, side by side.

    python benchmarks/bench_scale_before_after.py COMMIT [--places 2250] [--repeats 2]

COMMIT is an earlier commit of this repository whose ``scale`` is one file. Reads that
commit's ``vpr_explorer`` package with ``git archive`` into a temporary folder (the
repository is only read) and imports its one-file ``scale`` module
(``vpr_explorer/protocols/scale.py``, or ``vpr_explorer/scale.py`` in older commits; its own
private names: ``_blocked_pass``, ``_Entries``) with that commit's package under it, beside
this checkout's ``vpr_explorer.protocols.scale``; and on the same
Nordland-like data (``bench_nordland_scale.nordland_like``, places of 12 images, 50 splits)
times, alternating before/now ``--repeats`` times in this one process:

* the blocked pass alone (``_blocked_pass`` there, ``scale.blocked_pass.blocked_pass`` here, same
  inputs), and
* the whole ``scale_splits`` (full-set sums, automatic θ, pass, thresholds, scoring),

in CPU seconds of this process (all threads: steadier than wall time on a shared machine),
best of the repeats, with the pass's and the run's necessary flops (N²·D: each unordered
pair's similarity once) per CPU second as a share of numpy's float32 GEMM rate per CPU
second on the pass's block shape, measured in the same run. It checks that both give the
same outcomes (ranks, answered places and images, global θs) and per-place θs within 1e-8.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import io
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

import vpr_explorer.protocols.scale as now
from bench_nordland_scale import nordland_like
from gemm_peak import blas_kernel, gemm_rate, load_average
from vpr_explorer.protocols.evaluation import draw_splits
from vpr_explorer.protocols.options import BLOCK_ROWS, TABLE_MEMORY, ProtocolOptions
from vpr_explorer.protocols.scale.blocked_pass import blocked_pass
from vpr_explorer.protocols.scale.full_sums import full_set_sums
from vpr_explorer.protocols.scale.layout import as_layout32
from vpr_explorer.protocols.scale.panel import PassInputs
from vpr_explorer.protocols.scale.table import Entries

PASS_THREADS = len(os.sched_getaffinity(0))  # the pass's threads: every CPU this process may use
ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "vpr_explorer"
#: where the one-file module lies, by commit age
EARLIER_MODULES = ("vpr_explorer.protocols.scale", "vpr_explorer.scale")


def _package_modules() -> dict:
    return {name: m for name, m in sys.modules.items() if name == PACKAGE or name.startswith(PACKAGE + ".")}


def load_before(commit: str):
    """The one-file ``scale`` module of ``commit``, imported with that commit's own ``vpr_explorer``.

    Both packages live in this process: while the earlier one is imported, this checkout's
    modules are set aside in ``sys.modules`` and put back after; each package's modules keep
    the references they imported. (A name one of the earlier module's functions imports when
    it runs resolves to this checkout's module: only ``device`` runs do that.)

    Raises:
        SystemExit: ``commit`` is not a commit of this repository, or has no one-file ``scale`` module.
    """
    try:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", commit, PACKAGE],
                                 check=True, capture_output=True).stdout
    except subprocess.CalledProcessError as exc:
        sys.exit(f"before={commit!r}: git archive failed: {exc.stderr.decode().strip()}")
    folder = tempfile.mkdtemp(prefix="scale_before_")
    atexit.register(shutil.rmtree, folder, True)
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder)
    name = next((m for m in EARLIER_MODULES if (Path(folder) / (m.replace(".", "/") + ".py")).is_file()), None)
    if name is None:
        sys.exit(f"before={commit!r}: no one-file scale module in that commit; name an earlier one (e.g. 69166e8)")
    today = _package_modules()
    for m in today:
        del sys.modules[m]
    sys.path.insert(0, folder)
    try:
        module = importlib.import_module(name)
    finally:
        sys.path.remove(folder)
        for m in _package_modules():
            del sys.modules[m]
        sys.modules.update(today)
    if not Path(module.__file__).resolve().is_relative_to(Path(folder).resolve()):
        sys.exit(f"before={commit!r}: {name} was imported from {module.__file__}, not from the commit's files")
    return module


def run_pass_before(mod, x, labels, places, query_rows, centre, block):
    """The earlier module's pass, through its own names."""
    lay = mod.make_layout(labels, places, block)
    entries = mod._Entries(lay, mod.TABLE_MEMORY, None)
    try:
        mod._blocked_pass(x, lay, query_rows, None, entries, 10, (0.0, 0.3), centre, PASS_THREADS, None)
    finally:
        entries.close()


def run_pass_now(x, labels, places, query_rows, centre, block):
    """Today's pass on the same inputs."""
    lay = now.make_layout(labels, places, block)
    entries = Entries(lay, TABLE_MEMORY, None)
    try:
        blocked_pass(PassInputs(x, lay, query_rows, None, (0.0, 0.3), centre), entries, 10,
                     ProtocolOptions(block=block, threads=PASS_THREADS))
    finally:
        entries.close()


def cpu(fn):
    t0 = time.process_time()
    out = fn()
    return out, time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", help="an earlier commit of this repository whose scale module is one file")
    ap.add_argument("--places", type=int, default=2250, help="places of 12 images (default 2,250: 27,000 images)")
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    before = load_before(args.before)
    d, labels, trav = nordland_like(args.places, args.dim, 0)
    splits = draw_splits(labels, args.places, runs=args.runs, seed=0)
    lay = now.make_layout(labels, args.places, BLOCK_ROWS)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])
    centre = full_set_sums(d, lay, query_rows).centre
    x = as_layout32(d, lay)
    peak = gemm_rate(np.float32, 4096, args.dim, 4096, 3, clock=time.process_time)
    print(f"data: {len(d):,} images × {args.dim} in {args.places:,} places, {args.runs} splits; load average "
          f"{load_average()}")
    print(f"BLAS: {blas_kernel()}")
    mods = {"before": before, "now": now}
    passes = {"before": lambda *a: run_pass_before(before, *a), "now": run_pass_now}
    best_pass = {k: np.inf for k in mods}
    best_run = {k: np.inf for k in mods}
    results = {}
    for rep in range(args.repeats):
        for name, mod in mods.items():
            _, t = cpu(lambda: passes[name](x, labels, args.places, query_rows, centre, BLOCK_ROWS))
            best_pass[name] = min(best_pass[name], t)
            results[name], t_run = cpu(lambda: mod.scale_splits(d, labels, trav, args.places, splits))
            best_run[name] = min(best_run[name], t_run)
            print(f"  round {rep + 1}, {name:<6}: pass {t:7.2f} CPU s, whole run {t_run:7.2f} CPU s", flush=True)
    peak = max(peak, gemm_rate(np.float32, 4096, args.dim, 4096, 3, clock=time.process_time))
    needed = float(len(d)) ** 2 * args.dim

    def share(t: float) -> str:
        return f"{needed / t / 1e9:4.0f} GFLOP per CPU s = {100 * needed / t / 1e9 / peak:3.0f}% of peak"

    print(f"float32 GEMM (4096×{args.dim}) @ ({args.dim}×4096): {peak:.0f} GFLOP per CPU second (best of before and "
          "after)")
    for name in mods:
        print(f"{name:<6} pass {best_pass[name]:7.2f} CPU s ({share(best_pass[name])}); whole run "
              f"{best_run[name]:7.2f} CPU s ({share(best_run[name])})")
    print(f"now / before: pass {best_pass['now'] / best_pass['before']:.2f}×, whole run "
          f"{best_run['now'] / best_run['before']:.2f}× the CPU seconds (best of {args.repeats})")
    worst = 0.0
    for a, b in zip(results["before"], results["now"]):
        for key, oa in a.outcomes.items():
            for f in ("rank", "answer_place", "answer_image"):
                if not np.array_equal(getattr(oa, f), getattr(b.outcomes[key], f)):
                    sys.exit(f"error: {key} {f} differs between before and now")
        for key in ("auto", "oracle"):
            if a.thresholds[key] != b.thresholds[key]:
                sys.exit(f"error: the {key} θ differs between before and now")
        for key in ("simple", "weighted"):
            diff = np.abs(np.asarray(a.thresholds[key]) - np.asarray(b.thresholds[key]))
            worst = max(worst, float(np.nanmax(diff)))
    if worst > 1e-8:
        sys.exit(f"error: per-place θ differ by {worst:.1e} (> 1e-8)")
    print(f"same outcomes in every split; per-place θ within {worst:.1e}")


if __name__ == "__main__":
    main()
