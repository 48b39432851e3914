"""The entry points: ``scale_splits`` and ``fast_paper_protocol``, which run the package's steps in order.

Step 1's full-set sums (with step 4's automatic θs and the twins' content classes beside
them), step 2's pass, steps 1 and 3 per split, step 6's error bounds, then steps 5 and 6
together (package doc). With ``ProtocolOptions.device`` the full-set sums
(``full_sums.device_set_sums``) and the pass's panels run on that torch device; the rest
runs on the CPU.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.thresholds import pooled_pair_sample
from vpr_explorer.protocols.evaluation import (
    Evaluation,
    Progress,
    Protocol,
    Split,
    SplitScores,
    check_cross_condition,
    check_protocol_inputs,
    draw_splits,
    own_traversal_notes,
    paper_protocol,
    paper_settings,
    pooled_truth,
    split_pr,
    summarise,
)
from vpr_explorer.protocols.scale.blocked_pass import blocked_pass
from vpr_explorer.protocols.scale.downdate import split_mu, split_thresholds
from vpr_explorer.protocols.scale.full_sums import full_set_sums
from vpr_explorer.protocols.scale.layout import Layout, as_layout32, make_layout
from vpr_explorer.protocols.scale.near_ties import error_scale, uncertainty
from vpr_explorer.protocols.scale.panel import PassInputs
from vpr_explorer.protocols.scale.scoring import assemble, score_splits
from vpr_explorer.protocols.scale.table import Entries
from vpr_explorer.protocols.scale.twins import content_classes
from vpr_explorer.protocols.options import ProtocolOptions
from vpr_explorer.protocols.shared_scores import SharedScores

#: ``pr=True`` hands runs × places² up to this to ``paper_protocol`` (the per-place PR curves
#: score every query against every place at each of ~200 k).
PR_FAMILY_CELLS = 10_000_000


def automatic_thetas(d: np.ndarray, splits: list[Split], seed: int) -> list[float]:
    """Each split's automatic global θ from one pooled tile sample for the run (package doc, step 4)."""
    sample = pooled_pair_sample(d, [sp.train for sp in splits], seed=seed)
    return [sample.theta(r) for r in range(len(splits))]


def _now(fn: Callable, *args) -> Future:
    """``fn(*args)`` run now, in a finished future (``executor.submit``'s stand-in)."""
    future: Future = Future()
    future.set_result(fn(*args))
    return future


def _counting_from(progress: Progress | None, total: int, before: int) -> Callable[[int, str], None] | None:
    """``progress`` as a ``(done, message)`` callback whose count starts after ``before`` of ``total`` steps."""
    if progress is None:
        return None
    return lambda done, what: progress(before + done, total, what)


def _row_traversal(image_traversal: np.ndarray, lay: Layout) -> np.ndarray:
    """``(n_rows,)`` a code per traversal for every layout row, ``-1`` for padding."""
    _, codes = np.unique(image_traversal, return_inverse=True)
    row_traversal = np.full(lay.n_rows, -1, dtype=np.int64)
    real = lay.image_of_row >= 0
    row_traversal[real] = codes.ravel()[lay.image_of_row[real]]
    return row_traversal


def _scale_splits(d: np.ndarray, image_place: np.ndarray, image_traversal: np.ndarray, n_places: int,
                  splits: list[Split], options: ProtocolOptions, progress: Progress | None) -> list[SplitScores]:
    """``scale_splits`` on splits without unknown places."""
    lay = make_layout(image_place, n_places, options.block)
    query_rows = np.stack([lay.row_of_image[sp.queries] for sp in splits])  # (R, P): queries by place index
    held = lay.slot_of_row[query_rows]
    runs, threads = len(splits), options.threads
    n_pairs = lay.n_blocks * (lay.n_blocks + 1) // 2
    steps = runs + n_pairs + lay.n_blocks  # per split (automatic θ), per block pair, per row block
    with ThreadPoolExecutor(1) as aside:
        # in a thread beside the full-set sums (which leave a core idle now and then: their
        # lanes wait in turn), with more than one thread: the automatic θ (the reference's own
        # pooled sample, drawn once for the run) and the twins' content classes, which need
        # neither the sums nor the pass
        later = aside.submit if threads > 1 else _now
        autos, content = later(automatic_thetas, d, splits, options.seed), later(content_classes, d, lay)
        x = as_layout32(d, lay, threads)  # the pass's float32 rows, which the full-set sums read too
        sums = full_set_sums(d, lay, query_rows, threads, x, options.device)  # on the device where set
        mus = [split_mu(r, lay.row_of_image[sp.train], lay, sums, held[r]) for r, sp in enumerate(splits)]
        autos, content = autos.result(), content.result()
    report = _counting_from(progress, steps, 0)
    if report:
        for r in range(runs):
            report(r + 1, f"split {r + 1}/{runs}: automatic θ")
    # every θ_p is a convex combination of its place's μᵢ: all lie in [min μ, max μ] (the pass's floor)
    mu_range = (min(float(mu.min()) for mu, _ in mus), max(float(mu.max()) for mu, _ in mus))
    inputs = PassInputs(x, lay, query_rows,
                        _row_traversal(image_traversal, lay) if options.cross_condition else None, mu_range,
                        sums.centre)
    entries = Entries(lay, options.table_memory, options.spill_dir)
    try:
        pas = blocked_pass(inputs, entries, max(options.ks), options, progress=_counting_from(progress, steps, runs))
        del inputs, x  # the float32 layout rows: the pass was their last reader
        with ThreadPoolExecutor(threads) as pool:  # splits side by side: each writes only its own results
            data = list(pool.map(lambda r: split_thresholds(r, splits[r], lay, sums, pas.v, held[r], n_places,
                                                            autos[r], options.user_theta, content, mus[r]),
                                 range(runs)))
            kappa = error_scale(d, lay, sums, data, options.seed)
            for sd in data:
                sd.uncertainty = uncertainty(sd, lay, kappa)
            outs, tops = score_splits(entries, data, lay, pas, d, sums, _counting_from(progress, steps, runs + n_pairs))
            return list(pool.map(lambda r: assemble(data[r], outs[r], tops[r],
                                                    pas.best_own[query_rows[r]].astype(np.float64), image_place,
                                                    image_traversal, n_places), range(runs)))
    finally:
        entries.close()


def scale_splits(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    splits: list[Split],
    options: ProtocolOptions = ProtocolOptions(),
    *,
    progress: Progress | None = None,
) -> list[SplitScores]:
    """The paper protocol's splits scored through one blocked pass (see the package doc).

    Args:
        descriptors: ``(n_images, D)`` L2-normalised, any float dtype; read in row chunks,
            so a float16 memory-mapped array works and is never copied whole.
        image_place, image_traversal: ``(n_images,)`` labels (place ``-1``: a skipped frame).
        n_places: number of place ids.
        splits: from ``evaluation.draw_splits`` without unknown places.
        options: cross_condition (queries match other traversals only), user_theta (a global θ
            scored beside the automatic one), seed (the automatic threshold's pooled sample is
            drawn with it), ks (image-level ranks beyond max(ks) are reported as max(ks) + 1),
            and how the pass runs: block, table_memory, spill_dir, threads, device (the
            full-set sums and the pass's panels on that torch device).
        progress: ``progress(done, total, message)`` over the splits (their automatic θ), the
            pass's block pairs, then the scoring's row blocks.

    Returns:
        One ``SplitScores`` per split, with the reference's outcomes and thresholds. Its
        per-query matrices ``raw``/``best``/``correct`` are empty ``(0, n_places)`` (they
        are what this path avoids holding) and every ``Outcome.n_kept`` is ``-1``.

    Raises:
        VPRInputError: splits with unknown places.
    """
    if any(sp.unknown.any() for sp in splits):
        raise VPRInputError("scale_splits: splits with unknown places (the open set) are not supported; "
                            "use evaluation.open_set_protocol")
    return _scale_splits(descriptors, np.asarray(image_place), np.asarray(image_traversal), n_places, splits,
                         options, progress)


def fast_paper_protocol(
    descriptors: np.ndarray,
    image_place: np.ndarray,
    image_traversal: np.ndarray,
    n_places: int,
    options: ProtocolOptions = ProtocolOptions(),
    *,
    image_frame: np.ndarray | None = None,
    frame_place: np.ndarray | None = None,
    progress: Progress | None = None,
    settings: dict | None = None,
    shared: SharedScores | None = None,
) -> Evaluation:
    """``evaluation.paper_protocol`` through one blocked pass: the same ``Evaluation``.

    The same arguments and meaning as ``paper_protocol``; ``options``' block, table_memory,
    spill_dir, threads and device say how the pass runs (no number depends on them). The
    run goes to ``paper_protocol`` itself, and says so in the notes, when:

    * the tolerance makes a neighbouring place right for some query (places closer than
      the tolerance): the pass is built on one right place per query;
    * ``options.pr`` and runs × places² is at most ``PR_FAMILY_CELLS``: the per-place
      family curves need every query's raw_p, which the pass does not keep (above, they
      are left out). ``shared`` serves such a run only (a sweep builds one for all its cells).

    Returns:
        The ``Evaluation`` of ``paper_protocol``, its ``seconds`` this call's.

    Raises:
        VPRInputError: what ``paper_protocol`` raises on.
    """
    t0 = time.perf_counter()
    d, image_place, image_traversal = check_protocol_inputs(descriptors, image_place, image_traversal)
    check_cross_condition(image_place, image_traversal, options)
    runs, pr = options.runs, options.pr
    straight = None
    if pooled_truth(image_place, image_frame, frame_place, options.tolerance, n_places) is not None:
        straight = (f"a frame tolerance of {options.tolerance} makes neighbouring places right: scored by the "
                    "straightforward protocol (one right place per query is what the blocked pass assumes)")
    elif pr and runs * n_places**2 <= PR_FAMILY_CELLS:
        straight = ("precision–recall of the per-place methods needs every query's raw_p: scored by the "
                    "straightforward protocol (the same numbers)")
    if straight is not None:
        ev = paper_protocol(d, image_place, image_traversal, n_places, options, image_frame=image_frame,
                            frame_place=frame_place, progress=progress, settings=settings, shared=shared)
        return dataclasses.replace(ev, notes=(*ev.notes, straight), seconds=time.perf_counter() - t0)
    splits = draw_splits(image_place, n_places, runs=runs, seed=options.seed)
    scored = _scale_splits(d, image_place, image_traversal, n_places, splits, options, progress)
    notes = list(own_traversal_notes(options))
    pr_rows, pr_curves = split_pr(scored) if pr else ((), {})
    if pr:
        notes.append(f"precision–recall of the per-place methods left out: {runs} runs × {n_places:,}² places "
                     f"exceed {PR_FAMILY_CELLS:,} cells (the blocked pass keeps no raw_p)")
    return Evaluation(
        protocol=Protocol.PAPER, settings=paper_settings(options, settings, len(scored[0].known)),
        ks=options.ks, rows=summarise(scored, options.ks, own_traversal=True), notes=tuple(notes),
        seconds=time.perf_counter() - t0, pr=pr_rows, pr_curves=pr_curves,
    )
