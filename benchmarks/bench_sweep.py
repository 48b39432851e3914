"""A 6 × 6 group/step sweep on GardensPoint and Nordland_64x32: time per cell against one ``evaluate`` of it.

For each dataset: the descriptors are read once (the on-disk cache; timed apart), then
``sweep.sweep`` runs a 6 × 6 grid (groups 1–6 × steps 5–30, the stride reading: 35 cells
valid, group 6 step 5 would overlap) with the paper protocol and precision–recall (the AUC). Beside it, in the same
run, ``pipeline.evaluate_dataset`` — what ``vpr-explorer evaluate`` does: read the dataset,
its cached descriptors, run the protocol — for three cells of the grid (the fewest, the
middle and the most places), each compared with the sweep's time for that same cell. The
ratio sweep-cell / evaluate is what a sweep costs per cell against evaluating it alone,
in wall-clock seconds and in CPU seconds of this process (steadier on a shared machine);
the cells' numbers are checked equal to the evaluate's. Run::

    python benchmarks/bench_sweep.py --data /work/shared/datasets [--runs 5]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from vpr_explorer import settings
from vpr_explorer.datasets import load_dataset
from vpr_explorer.pipeline import dataset_descriptors, evaluate_dataset
from vpr_explorer.places import PlaceSpec
from vpr_explorer.sweep import SweepSpec, sweep

GROUPS = (1, 2, 3, 4, 5, 6)
STEPS = (5, 10, 15, 20, 25, 30)
DATASETS = ("GardensPointWalking", "Nordland_64x32")


def bench(root: Path, descriptor: str, runs: int, protocol: str) -> None:
    start = time.perf_counter()
    dataset = load_dataset(root)
    d = dataset_descriptors(dataset, descriptor)
    read = time.perf_counter() - start
    spec = SweepSpec(groups=GROUPS, steps=STEPS, readings=("stride",), protocol=protocol, runs=runs)
    cpu = [time.process_time()]  # after each cell: CPU seconds of this process (all its threads)

    def progress(done: int, total: int, message: str) -> None:
        cpu.append(time.process_time())
        print(f"  cell {done}/{total} ({message})", end="\r", file=sys.stderr)

    result = sweep(dataset, d, spec, descriptor=descriptor, progress=progress)
    print(" " * 60, end="\r", file=sys.stderr)
    cell_cpu = {c.spec: cpu[i + 1] - cpu[i] for i, c in enumerate(result.cells)}
    ran = [c for c in result.cells if not c.empty and c.same_as is None]
    for c in result.cells:
        if c.empty:
            print(f"  empty g{c.group} s{c.step}: {c.empty}")
    print(f"{dataset.name}: {dataset.n_images:,} images, {descriptor} {d.shape[1]}-d read in {read:.2f} s; "
          f"{len(result.cells)} cells ({len(ran)} run) in {result.seconds:.1f} s wall, "
          f"{sum(c.seconds for c in ran) / len(ran):.2f} s wall and "
          f"{sum(cell_cpu[c.spec] for c in ran) / len(ran):.2f} s CPU per cell "
          f"(places {min(c.n_places for c in ran)}–{max(c.n_places for c in ran)})")
    by_places = sorted(ran, key=lambda c: c.n_places)
    picks = [by_places[0], by_places[len(by_places) // 2], by_places[-1]]
    print(f"  {'cell':<16} {'places':>6} {'sweep cell wall/CPU s':>22} {'evaluate wall/CPU s':>20} "
          f"{'ratio wall':>10} {'ratio CPU':>9}  same numbers")
    walls, cpus = [], []
    for c in picks:
        t, p = time.perf_counter(), time.process_time()
        ev = evaluate_dataset(root, PlaceSpec(c.group, c.step, c.reading), descriptor, protocol, runs=runs, pr=True)
        seconds, cpu_s = time.perf_counter() - t, time.process_time() - p
        same = ev.same_numbers(c.evaluation) and c.auc == next(r.auc for r in ev.pr if r.key == spec.method)
        walls.append(c.seconds / seconds)
        cpus.append(cell_cpu[c.spec] / cpu_s)
        print(f"  g{c.group} s{c.step} {c.reading.value:<8} {c.n_places:>6} "
              f"{f'{c.seconds:.2f} / {cell_cpu[c.spec]:.2f}':>22} {f'{seconds:.2f} / {cpu_s:.2f}':>20} "
              f"{walls[-1]:>10.2f} {cpus[-1]:>9.2f}  {same}")
    print(f"  mean ratio sweep cell / evaluate: {sum(walls) / len(walls):.2f} wall, {sum(cpus) / len(cpus):.2f} CPU")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=settings.data_root(),
                        help=f"datasets folder (default ${settings.DATA_ENV})")
    parser.add_argument("--descriptor", default="pixels", help="descriptor (default pixels)")
    parser.add_argument("--runs", type=int, default=5, help="random splits per cell (default 5; the paper uses 50)")
    parser.add_argument("--protocol", default="paper", help="paper, traversal or open-set (default paper)")
    parser.add_argument("--only", choices=DATASETS, default=None, help="one of the two datasets")
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set ${settings.DATA_ENV}")
    print("$ python benchmarks/bench_sweep.py " + shlex.join(argv if argv is not None else sys.argv[1:]))
    print(f"{len(GROUPS)} × {len(STEPS)} sweep, groups {' '.join(map(str, GROUPS))} × steps "
          f"{' '.join(map(str, STEPS))}, stride reading; {args.protocol} protocol, {args.runs} runs, "
          "precision–recall on")
    for name in DATASETS if args.only is None else (args.only,):
        bench(args.data / name, args.descriptor, args.runs, args.protocol)


if __name__ == "__main__":
    main()
