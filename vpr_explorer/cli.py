"""Command line: ``vpr-explorer evaluate …`` (and the other sub-commands).

Bad input prints one ``error:`` line naming the file or parameter and exits 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vpr_explorer.errors import VPRInputError
from vpr_explorer.evaluation import K_GRID, Protocol
from vpr_explorer.places import PlaceSpec, Reading


def _bar(desc: str):
    from tqdm import tqdm

    state: dict = {}

    def update(done: int, total: int, *_):
        if "bar" not in state:
            state["bar"] = tqdm(total=total, desc=desc, unit="", file=sys.stderr, leave=False, dynamic_ncols=True)
        bar = state["bar"]
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    return update


def add_dataset_args(p: argparse.ArgumentParser) -> None:
    """Arguments shared by every sub-command that reads a dataset."""
    p.add_argument("--dataset", required=True, help="dataset folder, or 'demo' for the built-in route")
    p.add_argument("--group", type=int, default=3, help="consecutive frames per place (default 3)")
    p.add_argument("--step", type=int, default=10, help="frames from one place to the next (default 10)")
    p.add_argument("--reading", choices=[r.value for r in Reading], default=Reading.STRIDE.value,
                   help="stride: a place starts every STEP frames (authors' code); skip: take GROUP, skip STEP (paper text)")
    p.add_argument("--descriptor", default="efficientnet-lite0", help="descriptor name (default efficientnet-lite0)")
    p.add_argument("--cache-dir", type=Path, default=None, help="descriptor cache (default $VPR_EXPLORER_CACHE)")
    p.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="descriptor precision in memory and in the cache: float16 halves the descriptor memory "
                        "and disk, at about 1e-3 relative error in scores (default float32)")


def _evaluate(args: argparse.Namespace) -> int:
    from vpr_explorer.pipeline import evaluate_dataset
    from vpr_explorer.report import render

    ev = evaluate_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), args.descriptor, args.protocol,
        cache_root=args.cache_dir, extract_progress=_bar("descriptors"), dtype=args.dtype,
        runs=args.runs, seed=args.seed, cross_condition=args.cross_condition, unknown_share=args.unknown_share,
        database=args.database, queries=args.queries, tolerance=args.tolerance, user_theta=args.theta,
        k_grid=args.k, progress=_bar("splits"),
    )
    print(render(ev))
    if args.json:
        try:
            args.json.write_text(json.dumps(ev.to_dict(), indent=2, allow_nan=False, default=_json_default))
        except OSError as exc:
            raise VPRInputError(f"--json {args.json}: cannot write ({exc.strerror}); pick a writable path") from exc
        print(f"wrote {args.json}")
    return 0


def _record(args: argparse.Namespace) -> int:
    from vpr_explorer.recording import record_dataset

    playback = record_dataset(
        args.dataset, PlaceSpec(args.group, args.step, args.reading), args.descriptor,
        database=args.database, queries=args.queries, out=args.out, k=args.k, tolerance=args.tolerance,
        cache_root=args.cache_dir, extract_progress=_bar("descriptors"), progress=_bar("frames"), dtype=args.dtype,
    )
    print(playback.describe())
    print(f"wrote {playback.rrd}: watch it with `rerun {playback.rrd}` (or `rerun --web-viewer {playback.rrd}`)")
    return 0


def _json_default(o):
    raise TypeError(f"not JSON: {type(o)}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vpr-explorer", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    ev = sub.add_parser("evaluate", help="run a protocol and print the paper's kind of table")
    add_dataset_args(ev)
    ev.add_argument("--protocol", choices=[p.value for p in Protocol], default=Protocol.PAPER.value)
    ev.add_argument("--runs", type=int, default=50, help="random splits (paper: 50)")
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--cross-condition", action="store_true",
                    help="score each query only against database images of other traversals")
    ev.add_argument("--unknown-share", type=float, default=0.3, help="open set: share of places held out (default 0.3)")
    ev.add_argument("--k", type=float, nargs="+", default=list(K_GRID), help="open set: k values of θ_p + k·s_p")
    ev.add_argument("--database", nargs="+", default=None, help="traversal protocol: database traversal(s)")
    ev.add_argument("--queries", default=None, help="traversal protocol: query traversal")
    ev.add_argument("--tolerance", type=int, default=0, help="traversal protocol: frames of slack for a right place")
    ev.add_argument("--theta", type=float, default=None, help="also evaluate this global threshold")
    ev.add_argument("--json", type=Path, default=None, help="write the numbers to this JSON file")
    ev.set_defaults(func=_evaluate)

    rec = sub.add_parser("record", help="play a query traversal back against a database: write a rerun .rrd")
    add_dataset_args(rec)
    rec.add_argument("--database", nargs="+", required=True, help="database traversal(s), e.g. day_right")
    rec.add_argument("--queries", required=True, help="query traversal, e.g. night_right")
    rec.add_argument("--out", type=Path, required=True, help="the .rrd file to write, e.g. run.rrd")
    rec.add_argument("--k", type=float, default=0.0, help="thresholds θ_p + k·s_p (default 0: the paper's)")
    rec.add_argument("--tolerance", type=int, default=0, help="frames of slack for a right place (default 0)")
    rec.set_defaults(func=_record)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except VPRInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
