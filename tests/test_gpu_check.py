"""The prepared device check runs: ``benchmarks/gpu_check.py --device cpu --quick``, every step small.

On the device machine the same script gives the GPU figures; here it runs its steps on CPU
tensors (the figures mean nothing), so that the script a lent GPU's few minutes depend on is
known to work before it gets there: every step reports a row, the device paths agree with the
CPU's (descriptors to the tests' cosine, the protocol's numbers identical), and the logs
come back as the few files the device tool returns.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.realdata
def test_the_device_check_runs_every_step_on_the_cpu(data_root, tmp_path):
    logs = tmp_path / "logs"
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'benchmarks'}"}
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gpu_check.py"), "--device", "cpu", "--quick", "--logs", str(logs),
         "--data", str(data_root), "--skip", "tests"],
        capture_output=True, text=True, env=env, timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert sorted(p.name for p in logs.iterdir()) == ["check.log", "summary.md"]
    summary = (logs / "summary.md").read_text()
    assert "no GPU: the device steps ran on torch's cpu tensors" in summary
    rows = {line.split(" | ")[0].lstrip("| "): line.split(" | ")[1:] for line in summary.splitlines()
            if line.startswith("| ") and not line.startswith("| figure")}
    for figure in ("JPEG decode on cpu, batches of 8", "efficientnet-lite0 fp32: bare forward",
                   "efficientnet-lite0 fp32: end-to-end, JPEGs decoded on the device",
                   "efficientnet-lite0 bf16: end-to-end, JPEGs decoded on the CPU",
                   "paper protocol 720 × 64, 3 splits: device vs numpy pass",
                   "paper protocol 1,800 × 64: device vs numpy pass"):
        assert figure in rows, f"{figure!r} missing from:\n{summary}"
    assert rows["paper protocol 720 × 64, 3 splits: device vs numpy pass"][0] == "identical numbers"
    assert rows["paper protocol 1,800 × 64: device vs numpy pass"][0] == "identical numbers"
    least = float(rows["efficientnet-lite0 fp32: cosine, device vs CPU decode"][0].split()[-1])
    assert least > 0.9999
    assert not any(cells[0].startswith(("FAILED", "skipped")) for cells in rows.values()), summary
    assert summary in (logs / "check.log").read_text()  # the log holds everything printed, the table last


def test_the_check_reads_the_refit_time_off_bench_million(tmp_path):
    # the million step's figure is read off bench_million.py's report: a small database here
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'benchmarks'}"}
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_million.py"), "--database", "6000", "--queries", "200",
         "--skip-eval", "--device", "cpu", "--out", str(tmp_path)],
        capture_output=True, text=True, env=env, timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "fits' products: torch on cpu" in done.stdout
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from gpu_check import refit_time
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    moved, seconds = refit_time(done.stdout)
    assert moved == "25 m / 50 m (3,000 images)" and float(seconds) >= 0
    assert refit_time("no such line") is None
