"""The field's other acceptance rules beside the similarity matrix they read: time, and what each decides.

For each dataset, the value of two aligned traversals (``data.aligned.database_queries``,
one database traversal; ``method.sequences.check_sequence`` passes it as one ordered route
on each side), its descriptors in the value's order (``value_rows``), and:

* the similarity matrix, ``method.retrieval.similarity`` of the query rows against the
  database rows (float32 GEMM): the yardstick every other time is divided by;
* each rule's time on that matrix, and the ratio to it:

  - ``match_scores.top1_distance``, ``pa_ratio`` and ``sue`` (K 10, slope 350, clip 500 m):
    scores of the image-level top-1 answer, smaller = more confident;
  - ``query_threshold.query_thresholds`` (patch 20, KS test, mixture, Kalman filter);
    goal ≤ 5 s for 3,576 queries;
  - ``sequences.seqslam`` on the similarities (OpenSeqSLAM's defaults, ds 10); goal ≤ 2× the
    similarity matrix;
  - ``sequences.sequence_place_scores``: per-place raw_p of the sequence similarity, places
    group/step over frames (Nordland 3/3, GardensPoint 3/10);
  - ``graph_matcher.sequence_match`` (fan-out 5, the non-matching cost 1 − the median
    per-query threshold): the cheapest path alone;
  - ``tutorial_pr.tutorial_pr``: VPR_Tutorial's multi-match curve, soft ground truth ±2 frames
    as "ignore";
  - ``place_discovery.discover`` on the database descriptors in route order;
  - the whole bench, ``acceptance.acceptance_report`` (every rule, closed set and natural
    open set, group/step places), from the descriptors;

* what each decides, against the value's ground truth (the same frame):

  - SeqSLAM: Recall@1 of its match beside the single-image top-1's (over all queries, and
    over the queries SeqSLAM matches: the ds/2 at either end have no centred sequence);
  - per-query threshold: how many top-1 answers it accepts, and how many of those are right;
  - top-1 distance, PA-ratio, SUE: AUC of the precision–recall curve of the top-1 decision
    (``protocols.precision_recall.pr_curve``, which accepts score ≥ θ: given −score);
  - sequence place scores: place-level Recall@1 of the top place beside single-image raw_p;
  - place discovery: the number of places found and their sizes, beside group/step's.

**Positions for SUE.** The aligned traversals of Nordland carry no positions, and
GardensPoint's ``gp_pos.csv`` holds hand-made positions in [0, 1], not metres: SUE reads
frames spaced ``--spacing`` metres (default 10) along a straight line, and says so.

Every time is the best of ``--repeats`` runs (default 3) in one process, after the data are
loaded; the BLAS kernel the similarity matrix ran on is printed first
(``gemm_peak.blas_kernel``). ``--quick`` takes the first 600 frames of Nordland (queries and
database). Run::

    python benchmarks/bench_acceptance.py --data /work/shared/datasets [--quick] [--only nordland]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gemm_peak import blas_kernel, decision_flops
from vpr_explorer import settings
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.groundtruth import GroundTruth
from vpr_explorer.method.graph_matcher import sequence_match
from vpr_explorer.method.match_scores import pa_ratio, sue, top1_distance
from vpr_explorer.method.place_discovery import discover
from vpr_explorer.method.places import PlaceSpec, frame_places
from vpr_explorer.method.query_threshold import query_thresholds
from vpr_explorer.method.retrieval import place_scores, similarity, top_answer
from vpr_explorer.method.sequences import check_sequence, seqslam, sequence_place_scores
from vpr_explorer.pipeline import dataset_descriptors, resolve_dataset
from vpr_explorer.protocols.acceptance import acceptance_report
from vpr_explorer.protocols.precision_recall import pr_curve
from vpr_explorer.protocols.tutorial_pr import tutorial_pr

#: Frames of Nordland that ``--quick`` keeps, on both sides.
QUICK_FRAMES = 600
#: The per-query threshold's goal: seconds for this many queries.
QUERY_THRESHOLD_GOAL = (5.0, 3576)
#: SeqSLAM's goal: at most this many times the similarity matrix.
SEQSLAM_GOAL = 2.0


@dataclass(frozen=True)
class Case:
    """One dataset: where it is, which traversals, and its group/step places."""

    key: str
    folder: str
    query: str
    database: str
    spec: PlaceSpec


CASES = (
    Case("nordland", "Nordland_64x32", "winter", "summer", PlaceSpec(3, 3)),
    Case("gardens", "GardensPointWalking", "night_right", "day_right", PlaceSpec(3, 10)),
)


def timed(fn, repeats: int) -> tuple[float, object]:
    """Best of ``repeats`` wall-clock seconds, and the last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def load(data: Path, case: Case, descriptor: str, frames: int | None):
    """The value, its (queries, database) descriptors, and its same-frame ground truth, cut to ``frames``."""
    dataset = resolve_dataset(data / case.folder)
    value = database_queries(dataset, case.query, database=[case.database])
    check_sequence(value)
    desc = dataset_descriptors(dataset, descriptor)
    rows = value_rows(value)
    d = desc if rows is None else desc[rows]
    n_db, n_q = value.n_database, value.n_queries
    if frames is not None:
        n_db, n_q = min(n_db, frames), min(n_q, frames)
    db, queries = d[:n_db], d[value.n_database:value.n_database + n_q]
    truth = GroundTruth.from_frames(value.query_frame[:n_q], value.database_frame[:n_db], 0)
    return value, np.ascontiguousarray(queries), np.ascontiguousarray(db), truth


def auc(score: np.ndarray, right: np.ndarray, known: np.ndarray) -> float:
    """AUC-PR of accepting the top-1 answer when score ≤ τ (smaller = more confident)."""
    return pr_curve(-score, right, known).auc


def bench(data: Path, case: Case, descriptor: str, repeats: int, spacing: float, frames: int | None) -> None:
    value, q, db, truth = load(data, case, descriptor, frames)
    n_q, n_db, dim = len(q), len(db), q.shape[1]
    cut = f", first {frames} frames" if frames is not None else ""
    print(f"\n{case.folder}: {case.query} against {case.database}, {descriptor}{cut}: "
          f"{n_q:,} queries × {n_db:,} database images, D = {dim}; check_sequence passed "
          "(one ordered traversal on each side)")
    why = ("the traversals carry no positions" if value.database_xy is None
           else "the dataset's positions file is not in metres and is not used")
    print(f"  SUE positions: frames {spacing:g} m apart along a line ({why})")

    t_sim, sims = timed(lambda: similarity(q, db), repeats)
    xy = np.c_[np.arange(n_db) * spacing, np.zeros(n_db)]
    db_place = frame_places(n_db, case.spec)
    n_places = int(db_place.max()) + 1
    # images between places get a spare id whose column is dropped (place_scores wants ids ≥ 0)
    labels = np.where(db_place >= 0, db_place, n_places)

    def seq_places():
        raw, best = sequence_place_scores(sims, labels, n_places + 1)
        return raw[:, :n_places], best[:, :n_places]

    nmc = 1.0 - float(np.median(query_thresholds(sims, ordered=value.ordered).threshold))
    hard, soft = truth.dense(), GroundTruth.from_frames(value.query_frame[:n_q], value.database_frame[:n_db], 2).dense()
    whole = None
    if frames is None:
        d_value = np.concatenate([db, q])
        whole = ("the whole bench (acceptance_report)",
                 lambda: acceptance_report(value, d_value, labels=db_place, settings={"descriptor": descriptor}))

    steps = (
        ("top-1 distance (L2)", lambda: top1_distance(sims)),
        ("PA-ratio", lambda: pa_ratio(sims)),
        ("SUE", lambda: sue(sims, xy)),
        ("per-query threshold", lambda: query_thresholds(sims, ordered=value.ordered)),
        ("SeqSLAM", lambda: seqslam(sims, kind="similarity")),
        (f"sequence place scores {case.spec.group}/{case.spec.step}", seq_places),
        ("graph matcher (fan-out 5)", lambda: sequence_match(sims, non_matching_cost=nmc, fanout=5)),
        ("VPR_Tutorial PR, multi-match, soft ignored", lambda: tutorial_pr(sims, hard, soft, matching="multi")),
        ("place discovery (database)", lambda: discover(db)),
        *([whole] if whole is not None else []),
    )
    gflops = decision_flops(n_q, n_db, dim) / t_sim / 1e9
    print(f"  {'step':<42}{'best ms':>10}{'× similarity':>14}")
    print(f"  {'similarity matrix (retrieval.similarity)':<42}{t_sim * 1e3:>10.1f}{1.0:>13.2f}x   "
          f"{gflops:.0f} GFLOP/s (2·F·N·D)")
    times, out = {}, {}
    for name, fn in steps:
        times[name], out[name] = timed(fn, repeats)
        print(f"  {name:<42}{times[name] * 1e3:>10.1f}{times[name] / t_sim:>13.2f}x", flush=True)

    goal_s = QUERY_THRESHOLD_GOAL[0] * n_q / QUERY_THRESHOLD_GOAL[1]
    t_qt = times["per-query threshold"]
    pro_rata = "" if n_q == QUERY_THRESHOLD_GOAL[1] else f", {goal_s:.2f} s pro rata for {n_q:,}"
    print(f"  goal, per-query threshold ≤ {QUERY_THRESHOLD_GOAL[0]:g} s for {QUERY_THRESHOLD_GOAL[1]:,} queries"
          f"{pro_rata}: {t_qt:.2f} s, {'met' if t_qt <= goal_s else 'MISSED'}")
    r_seq = times["SeqSLAM"] / t_sim
    print(f"  goal, SeqSLAM ≤ {SEQSLAM_GOAL:g}× the similarity matrix: {r_seq:.2f}×, "
          f"{'met' if r_seq <= SEQSLAM_GOAL else 'MISSED'}")

    # what each decides
    positives = truth.dense()
    known = truth.known
    rows = np.arange(n_q)
    l2, pa, su = out["top-1 distance (L2)"], out["PA-ratio"], out["SUE"]
    top1 = l2.top1
    right = positives[rows, top1]
    print(f"  decides, top-1 decision AUC-PR (same frame; single-image Recall@1 {right.mean():.3f}): "
          f"L2 {auc(l2.score, right, known):.3f}, PA-ratio {auc(pa.score, right, known):.3f}, "
          f"SUE {auc(su.score, right, known):.3f}")

    qt = out["per-query threshold"]
    acc = qt.accepted
    acc_right = positives[rows, qt.best_match] & acc
    precision = acc_right.sum() / acc.sum() if acc.any() else float("nan")
    print(f"  decides, per-query threshold: accepts {acc.sum():,} of {n_q:,} top-1 answers "
          f"({acc_right.sum():,} right, precision {precision:.3f}); {qt.bimodal.sum():,} patches bimodal")

    seq = out["SeqSLAM"]
    m = seq.matched
    seq_right = positives[rows, np.maximum(seq.match, 0)] & m
    print(f"  decides, SeqSLAM Recall@1 (same frame) {seq_right.mean():.3f} vs single-image top-1 "
          f"{right.mean():.3f} over all {n_q:,} queries; {seq_right[m].mean():.3f} vs {right[m].mean():.3f} over "
          f"the {m.sum():,} it matches")

    raw_seq, _ = out[f"sequence place scores {case.spec.group}/{case.spec.step}"]
    keep = db_place >= 0
    raw_one, _ = place_scores(sims[:, keep], db_place[keep], n_places)
    place_truth = truth.places(labels, n_places + 1)[:, :n_places]
    place_known = place_truth.any(axis=1)
    seq_rows = place_known & np.isfinite(raw_seq).any(axis=1)

    def place_r1(raw: np.ndarray, mask: np.ndarray) -> float:
        top = top_answer(raw[mask])
        return float((place_truth[mask][np.arange(mask.sum()), top] & (top >= 0)).mean())

    print(f"  decides, place-level Recall@1 ({n_places:,} places {case.spec.group}/{case.spec.step}, the "
          f"{seq_rows.sum():,} queries with a place and a sequence): sequence raw_p {place_r1(raw_seq, seq_rows):.3f} "
          f"vs single-image raw_p {place_r1(raw_one, seq_rows):.3f}")

    found = out["place discovery (database)"]
    sizes = found.sizes
    grid_sizes = np.bincount(db_place[keep])
    print(f"  decides, place discovery: {found.n_places:,} places (sizes min {sizes.min()}, median "
          f"{np.median(sizes):g}, max {sizes.max()}; {np.count_nonzero(found.place < 0)} trailing frame(s) left out) "
          f"vs group/step {case.spec.group}/{case.spec.step}: {n_places:,} places of {grid_sizes.min()}"
          f"{'' if grid_sizes.min() == grid_sizes.max() else f'–{grid_sizes.max()}'} frames")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=settings.data_root(),
                        help=f"datasets folder (default ${settings.DATA_ENV})")
    parser.add_argument("--descriptor", default="pixels", help="descriptor name (default pixels)")
    parser.add_argument("--repeats", type=int, default=3, help="best of this many runs of each step (default 3)")
    parser.add_argument("--spacing", type=float, default=10.0,
                        help="metres between frames, the positions SUE reads (default 10)")
    parser.add_argument("--only", choices=[c.key for c in CASES], help="run one dataset")
    parser.add_argument("--quick", action="store_true",
                        help=f"Nordland's first {QUICK_FRAMES} frames only (queries and database)")
    args = parser.parse_args(argv)
    if args.data is None:
        parser.error(f"give --data or set {settings.DATA_ENV}")
    if args.repeats < 1:
        parser.error("--repeats must be 1 or more")
    if not args.spacing > 0:
        parser.error("--spacing must be a positive number of metres")
    print("$ python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]))
    print(f"BLAS: {blas_kernel()}")
    print(f"best of {args.repeats}")
    for case in CASES:
        if args.only in (None, case.key):
            frames = QUICK_FRAMES if args.quick and case.key == "nordland" else None
            bench(args.data, case, args.descriptor, args.repeats, args.spacing, frames)


if __name__ == "__main__":
    main()
