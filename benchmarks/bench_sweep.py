"""A 6 × 6 group/step sweep on GardensPoint and Nordland_64x32: time per cell against one ``evaluate`` of it.

For each dataset: the descriptors are read once (the on-disk cache; timed apart), then
``sweep.sweep`` (its stages: ``vpr_explorer.pipeline``) runs a 6 × 6 grid (groups 1–6 ×
steps 5–30, the stride reading: 35 cells valid, group 6 step 5 would overlap) with the paper
protocol and precision–recall (the AUC).
The sweep shares one ``shared_scores.SharedScores`` between its cells (the float32
similarity of all images and the float64 Gram the negative statistics come from); the
first cell builds it, and that one-off cost is also timed on its own. Beside it, in the
same run, for three cells of the grid (the fewest, the middle and the most places):

* **alone**: the same cell by ``pipeline.run_protocol`` without shared scores, so it
  builds its own (what every cell cost if nothing were shared between cells);
* **evaluate**: ``pipeline.evaluate_dataset``, what ``vpr-explorer evaluate`` does: read
  the dataset, its cached descriptors, run the protocol (building its own shared scores).

Ratios are the sweep's cell over each, in wall-clock seconds and in CPU seconds of this
process (steadier on a shared machine); the numbers of all three are checked equal, bit
for bit. Run::

    python benchmarks/bench_sweep.py --data /work/shared/datasets [--runs 5] [--only GardensPointWalking]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from vpr_explorer import pipeline, settings
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.pipeline import dataset_descriptors, evaluate_dataset, run_protocol
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.shared_scores import SHARED_LIMIT, SharedScores
from vpr_explorer.protocols.sweep import SweepSpec, sweep

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

    result = sweep(dataset, d, spec, pipeline, descriptor=descriptor, progress=progress)
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
          f"(places {min(c.n_places for c in ran)}–{max(c.n_places for c in ran)}); after the first cell "
          f"{sum(c.seconds for c in ran[1:]) / max(1, len(ran) - 1):.2f} s wall and "
          f"{sum(cell_cpu[c.spec] for c in ran[1:]) / max(1, len(ran) - 1):.2f} s CPU per cell")
    if dataset.n_images <= SHARED_LIMIT:
        t, p = time.perf_counter(), time.process_time()
        alone = SharedScores(d)
        alone.full(), alone.gram()
        print(f"  shared scores ({dataset.n_images:,}² float32 similarity and float64 Gram), built once by the "
              f"first cell: {time.perf_counter() - t:.2f} s wall, {time.process_time() - p:.2f} s CPU")
        del alone
    else:
        print(f"  {dataset.n_images:,} images > {SHARED_LIMIT:,}: no shared scores, every cell in closed form")
    # the first cell run also builds the shared scores: the three compared cells are picked from the others
    by_places = sorted(ran[1:], key=lambda c: c.n_places)
    picks = [by_places[0], by_places[len(by_places) // 2], by_places[-1]]
    print(f"  {'cell':<16} {'places':>6} {'sweep cell':>13} {'alone':>13} {'evaluate':>13} "
          f"{'sweep/alone':>12} {'sweep/evaluate':>15}  same numbers")
    print(f"  {'':<16} {'':>6} {'wall/CPU s':>13} {'wall/CPU s':>13} {'wall/CPU s':>13} "
          f"{'wall / CPU':>12} {'wall / CPU':>15}")
    ratios = {"alone": ([], []), "evaluate": ([], [])}
    options = ProtocolOptions(**spec.options(), pr=spec.pr)  # what each of the sweep's cells runs with
    for c in picks:
        spec_c = PlaceSpec(c.group, c.step, c.reading)
        t, p = time.perf_counter(), time.process_time()
        solo = run_protocol(protocol, dataset, make_places(dataset, spec_c), d, options,
                            settings={"descriptor": descriptor, "dtype": str(d.dtype)})
        solo_s = (time.perf_counter() - t, time.process_time() - p)
        t, p = time.perf_counter(), time.process_time()
        ev = evaluate_dataset(root, spec_c, descriptor, protocol, options)
        eval_s = (time.perf_counter() - t, time.process_time() - p)
        cell_s = (c.seconds, cell_cpu[c.spec])
        auc = next(r.auc for r in ev.pr if r.key == spec.method)
        same = (ev.same_numbers(c.evaluation) and ev.same_numbers(solo) and c.auc == auc
                and next(r.auc for r in solo.pr if r.key == spec.method) == auc)
        cells = []
        for name, other in (("alone", solo_s), ("evaluate", eval_s)):
            w, u = cell_s[0] / other[0], cell_s[1] / other[1]
            ratios[name][0].append(w)
            ratios[name][1].append(u)
            cells.append(f"{w:.2f} / {u:.2f}")
        print(f"  g{c.group} s{c.step} {c.reading.value:<8} {c.n_places:>6} "
              f"{f'{cell_s[0]:.2f} / {cell_s[1]:.2f}':>13} {f'{solo_s[0]:.2f} / {solo_s[1]:.2f}':>13} "
              f"{f'{eval_s[0]:.2f} / {eval_s[1]:.2f}':>13} {cells[0]:>12} {cells[1]:>15}  {same}")
    for name, (w, u) in ratios.items():
        print(f"  mean ratio sweep cell / {name}: {sum(w) / len(w):.2f} wall, {sum(u) / len(u):.2f} CPU")


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
