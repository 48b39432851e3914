"""Real Nordland (64×32, summer and winter, 3,576 frames each) with the pixel descriptor.

    VPR_EXPLORER_DATA=../shared/datasets python benchmarks/bench_nordland_real.py [--runs 50] [--reference]

Runs, and prints the tables and times of,

* the paper protocol with group 3, step 3 (1,192 places × 6 images) through
  ``scale.fast_paper_protocol`` (``--cross-condition`` for the cross-condition variant), and
* the traversal protocol summer → winter (``pipeline.run_protocol``).

``--reference`` also runs ``evaluation.paper_protocol`` and checks the tables are identical
(about 15–25 minutes for 50 splits on 2 cores).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time


from vpr_explorer.pipeline import dataset_descriptors, run_protocol
from vpr_explorer.method.places import PlaceSpec, make_places
from vpr_explorer.views.report import render
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.scale import fast_paper_protocol
from vpr_explorer.settings import data_root


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cross-condition", action="store_true")
    ap.add_argument("--reference", action="store_true", help="also run paper_protocol and compare")
    args = ap.parse_args()
    root = data_root()
    if root is None:
        sys.exit("set VPR_EXPLORER_DATA to the shared datasets folder (e.g. ../shared/datasets)")

    from vpr_explorer.data.traversals import load_dataset

    t0 = time.perf_counter()
    dataset = load_dataset(root / "Nordland_64x32")
    desc = dataset_descriptors(dataset, "pixels")
    print(f"{dataset.name}: {dataset.n_images} images ({', '.join(dataset.traversals)}), pixel descriptors "
          f"{desc.shape} in {time.perf_counter() - t0:.1f} s")

    places = make_places(dataset, PlaceSpec(3, 3))
    settings = {"dataset": dataset.name, "places": places.describe(), "descriptor": "pixels"}
    t0 = time.perf_counter()
    options = ProtocolOptions(runs=args.runs, seed=args.seed, cross_condition=args.cross_condition)
    ev = fast_paper_protocol(desc, places.image_place, dataset.image_traversal, places.n_places, options,
                             settings=settings)
    print(f"\npaper protocol, fast path: {time.perf_counter() - t0:.1f} s\n")
    print(render(ev))

    if args.reference:
        from vpr_explorer.protocols.evaluation import paper_protocol

        t0 = time.perf_counter()
        ref = paper_protocol(desc, places.image_place, dataset.image_traversal, places.n_places, options,
                             settings=settings)
        same = ref.same_numbers(ev)
        print(f"\npaper_protocol (straightforward): {time.perf_counter() - t0:.1f} s; identical tables: {same}")

    t0 = time.perf_counter()
    trav = run_protocol("traversal", dataset, places, desc, ProtocolOptions(database=["summer"], queries="winter"),
                        settings={"descriptor": "pixels"})
    print(f"\ntraversal protocol summer → winter: {time.perf_counter() - t0:.1f} s\n")
    print(render(trav))
    print(f"\npeak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    main()
