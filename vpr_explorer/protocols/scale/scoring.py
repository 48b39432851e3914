"""Per split and row block: candidates, every method's ranks and answers, ``SplitScores`` (package doc, steps 5, 6).

Each query's table entries at or above its cutoff (``candidate_cutoff``) are its candidates
(``candidates``), from which every method of ``METHOD_ORDER`` follows
(``score_place_level``, ``score_image_level``). Where an outcome hangs on a comparison that
a weighted θ within its error bound could overturn (``near_tie_places``), those places are
made exact (``near_ties.make_exact``) and the block is scored again (``score_splits``).
``assemble`` adds the global θs and returns the split as the reference has it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.retrieval import METHODS_BY_KEY, Outcome
from vpr_explorer.protocols.evaluation import SplitScores, oracle_global_threshold
from vpr_explorer.protocols.scale.blocked_pass import PassResult
from vpr_explorer.protocols.scale.downdate import SplitData
from vpr_explorer.protocols.scale.full_sums import FullSums
from vpr_explorer.protocols.scale.layout import Layout
from vpr_explorer.protocols.scale.near_ties import make_exact
from vpr_explorer.protocols.scale.table import TIE, Entries, Records, round_down32


def _first_argmax(score: np.ndarray, seg: np.ndarray, seg_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per segment: the largest score and the first element within the tie tolerance of it
    (−1 where all are −inf)."""
    top = np.maximum.reduceat(score, seg)
    idx = np.where(score >= top[seg_of] - TIE, np.arange(len(score)), len(score))
    first = np.minimum.reduceat(idx, seg)
    first[~np.isfinite(top)] = -1
    return top, first


def candidate_cutoff(b: np.ndarray, own: np.ndarray, th_s: np.ndarray, th_w: np.ndarray,
                     unc_w: np.ndarray) -> np.ndarray:
    """Per query, the lowest raw score that can reach any method's rank or answer (package doc, step 5).

    Args:
        b: ``(n,)`` each query's best correct score (``-inf``: none); own: its place index.
        th_s, th_w: ``(P,)`` simple and weighted θ per place index; unc_w: the weighted θ's
            error bounds (package doc, step 6).
    Returns:
        ``(n,)`` float32, rounded down. Places at or above b − tie count for the baselines and
        the global θs. Under a per-place θ, with the own place kept (b ≥ θ_own) a place counts
        if its margin ties or beats the own one, raw ≥ θ_p + (b − θ_own) − tie; with it
        dropped, any kept place may be the answer, raw ≥ θ_p. Both are at least
        min θ + max(b − θ_own, 0) − tie. The
        weighted θs enter at their bounds' lowest θ_p and highest θ_own, so that a place
        below the cutoff matters under no θ within the bounds, and the near-tie check sees
        every place that might.
    """
    cut = b
    for low, high in ((th_s, th_s), (th_w - unc_w, th_w + unc_w)):
        cut = np.minimum(cut, float(np.min(low)) + np.maximum(b - high[own], 0.0))
    return round_down32(cut - TIE - 1e-12)


#: The methods scored per block, in the reference's order (the global θs follow in ``assemble``).
METHOD_ORDER = ("image-baseline", "place-baseline", "margin-simple", "margin-weighted", "raw-simple", "raw-weighted")


@dataclass(frozen=True, eq=False)
class Candidates:
    """One split's queries of a row block and their candidate places, query by query (package doc, step 5).

    Per query ``(G,)``: ``own`` its place index (= its position among the split's queries),
    ``row`` its layout row, ``b`` its best correct score (``-inf``: none).
    Per candidate ``(n,)``, grouped by query and in place order within one (``start``: each
    query's first): ``query`` (position in the block), ``place`` (place index), ``t1``/``t2``
    the place's best and second-best score over all its images, ``held`` its held-out slot,
    ``hit`` whether its best image is the held-out one, ``raw`` raw_p in this split (``t2`` on
    a hit, else ``t1``) and ``image`` the lowest-index training image within the tie tolerance
    of it. ``near`` indexes the candidates whose place has images within the tolerance of
    each other, ``slots`` their ``(len(near), m)`` slot scores (held-out and padding ``-inf``)
    and ``near_images`` the training image of each of those slots.
    """

    own: np.ndarray
    row: np.ndarray
    b: np.ndarray
    query: np.ndarray
    start: np.ndarray
    place: np.ndarray
    t1: np.ndarray
    t2: np.ndarray
    held: np.ndarray
    hit: np.ndarray
    raw: np.ndarray
    image: np.ndarray
    near: np.ndarray
    slots: np.ndarray
    near_images: np.ndarray

    @property
    def is_own(self) -> np.ndarray:
        return self.place == self.own[self.query]


def candidates(ent: dict[str, np.ndarray], blk: int, sd: SplitData, lay: Layout, pas: PassResult,
               th_s: np.ndarray, th_w: np.ndarray) -> Candidates:
    """The table entries of the block's queries at or above their cutoffs, with raw_p of the split."""
    own = np.arange(lay.block_start[blk], lay.block_start[blk + 1])  # the block's places = its queries
    qrow = lay.row_of(own, sd.held[own])
    b = pas.best_own[qrow].astype(np.float64)
    cut32 = candidate_cutoff(b, own, th_s, th_w, sd.uncertainty)
    local = qrow - lay.rows(blk).start
    start, count = ent["ptr"][local], ent["ptr"][local + 1] - ent["ptr"][local]
    qi = np.repeat(np.arange(len(own)), count)
    idx = np.arange(len(qi)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
    keep = ent["t1"][idx] >= cut32[qi]
    idx, qi = idx[keep], qi[keep]
    seg = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
    if len(seg) != len(own):  # pragma: no cover - the own place is always an entry above the cutoff
        raise RuntimeError("internal error: a query without its own place among the candidates")
    pc, t1, t2 = ent["place"][idx].astype(np.int64), ent["t1"][idx], ent["t2"][idx]
    a1, a2 = ent["a1"][idx], ent["a2"][idx]
    held = sd.held[pc]
    hit = a1 == held  # the best image of that place is the one held out: its second counts
    raw = np.where(hit, t2, t1).astype(np.float64)
    slot = np.where(hit, a2, a1).astype(np.int64)
    near = np.flatnonzero(ent["near"][idx])
    slots = np.empty((0, lay.slots), dtype=np.float32)
    near_images = np.empty((0, lay.slots), dtype=np.int64)
    if len(near):  # several images of the place within the tolerance: raw_p and its image from every slot
        slots = pas.near.lookup(qrow[qi[near]], pc[near]).copy()
        slots[np.arange(len(near)), held[near]] = -np.inf
        top = slots.max(axis=1)
        raw[near] = top
        slot[near] = np.argmax(slots >= top[:, None].astype(np.float64) - TIE, axis=1)
        m = lay.slots
        near_images = lay.image_of_row[lay.row_of(np.repeat(pc[near], m), np.tile(np.arange(m), len(near)))]
        near_images = near_images.reshape(len(near), m)
    image = lay.image_of_row[lay.row_of(pc, slot)]
    return Candidates(own, qrow, b, qi, seg, pc, t1, t2, held, hit, raw, image, near, slots, near_images)


def score_place_level(c: Candidates, th_s: np.ndarray, th_w: np.ndarray, places: np.ndarray,
                      out: dict[str, dict[str, np.ndarray]]) -> np.ndarray:
    """The place-level methods of ``METHOD_ORDER`` into ``out``; returns each query's top raw score."""
    qi, seg, pc, raw, own = c.query, c.start, c.place, c.raw, c.own
    is_own, bq = c.is_own, c.b[qi]

    def put(key, rank, first):
        o = out[key]
        o["rank"][own] = rank
        o["place"][own] = np.where(first >= 0, places[pc[np.maximum(first, 0)]], -1)
        o["image"][own] = np.where(first >= 0, c.image[np.maximum(first, 0)], -1)

    tied = bq - TIE
    rank_base = np.where(np.isfinite(c.b), 1.0 + np.add.reduceat((raw >= tied) & ~is_own, seg), np.inf)
    top, first = _first_argmax(raw, seg, qi)
    put("place-baseline", rank_base, first)
    for name, th in (("simple", th_s), ("weighted", th_w)):
        thc = th[pc]
        kept = raw >= thc
        kept_own = c.b >= th[own]
        score = np.where(kept, raw, -np.inf)
        _, f = _first_argmax(score, seg, qi)
        put(f"raw-{name}", np.where(kept_own, 1.0 + np.add.reduceat((score >= tied) & ~is_own, seg), np.inf), f)
        margin = np.where(kept, raw - thc, -np.inf)
        _, f = _first_argmax(margin, seg, qi)
        m_own = (c.b - th[own])[qi]
        put(f"margin-{name}",
            np.where(kept_own, 1.0 + np.add.reduceat((margin >= m_own - TIE) & ~is_own, seg), np.inf), f)
    return top


def near_tie_places(c: Candidates, th_w: np.ndarray, uncertainty: np.ndarray) -> np.ndarray:
    """Places whose weighted θ must be exact before these outcomes can be trusted (package doc, step 6).

    A comparison is doubtful when the θs' error bounds could overturn it: a candidate's keep
    test, its margin against the own place's less the tie tolerance (the rank), or against
    the top margin less the tolerance (the answer, the lowest place within it); and the own
    place's keep test. Every place of a doubtful comparison is returned.
    """
    qi, seg, pc, own = c.query, c.start, c.place, c.own
    unc = uncertainty[pc]
    u_own = uncertainty[own]
    m_all = c.raw - th_w[pc]
    m_own = (c.b - th_w[own])[qi]
    kept_m = np.where(c.raw >= th_w[pc], m_all, -np.inf)
    top_w, f_w = _first_argmax(kept_m, seg, qi)
    idx = np.where(kept_m == top_w[qi], np.arange(len(pc)), len(pc))  # the place reaching the top itself
    p_top = np.minimum.reduceat(idx, seg)
    p_top[~np.isfinite(top_w)] = -1
    u_top = np.where(p_top >= 0, unc[np.maximum(p_top, 0)], 0.0)[qi]
    with np.errstate(invalid="ignore"):  # −inf − −inf: NaN, never near
        near = (np.abs(m_all) <= unc) & (unc > 0)  # kept or not
        near |= (np.abs(m_all - (m_own - TIE)) <= unc + u_own[qi]) & (unc + u_own[qi] > 0) & ~c.is_own
        near |= ((np.abs(m_all - (top_w[qi] - TIE)) <= unc + u_top) & (unc + u_top > 0)
                 & (np.arange(len(pc)) != p_top[qi]) & np.isfinite(top_w[qi]))
        flagged = (np.add.reduceat(near, seg) > 0) | ((np.abs(c.b - th_w[own]) <= u_own) & (u_own > 0))
    if not flagged.any():
        return np.empty(0, np.int64)
    top_place = np.where(f_w >= 0, pc[np.maximum(f_w, 0)], own)
    peak_place = np.where(p_top >= 0, pc[np.maximum(p_top, 0)], own)
    return np.unique(np.concatenate([pc[near & flagged[qi]], own[flagged], top_place[flagged], peak_place[flagged]]))


def score_image_level(c: Candidates, top: np.ndarray, records: Records, slots: int,
                      out: dict[str, dict[str, np.ndarray]]) -> None:
    """The image-level baseline into ``out`` (its answered place is filled in by ``assemble``).

    The top image is the lowest-index training image within the tie tolerance of the top
    score; the rank counts the wrong training images within it of b or above, resolved up to
    ``records.cap``.
    """
    qi, seg, pc = c.query, c.start, c.place
    bq, finite = c.b[qi] - TIE, np.isfinite(c.b)
    cap = records.cap
    floor_top = top[qi] - TIE
    tied = (c.raw >= floor_top) & np.isfinite(top[qi])
    image = c.image.copy()  # outside the near-duplicate places only raw_p's image can reach the top
    if len(c.near):
        ok = c.slots >= floor_top[c.near][:, None]
        slot = np.argmax(ok, axis=1)
        image[c.near] = np.where(ok.any(axis=1), c.near_images[np.arange(len(c.near)), slot], c.image[c.near])
    img_top = np.minimum.reduceat(np.where(tied, image, np.iinfo(np.int64).max), seg)
    img_top[~np.isfinite(top)] = -1
    above = (c.t1 >= bq) & ~c.is_own & finite[qi]
    contrib = np.where(above & (c.t2 < bq), (~c.hit).astype(np.int64), 0)  # one image reaches b: unless held out
    multi = np.flatnonzero(above & (c.t2 >= bq))
    beyond = np.zeros(len(c.own), dtype=bool)
    if len(multi):  # two or more images reach b: count them from the records
        mrow = c.row[qi[multi]]
        over = records.n[mrow] >= cap
        match = records.place[mrow] == pc[multi][:, None]
        found = match.any(axis=1)
        bits = records.bits[mrow, np.argmax(match, axis=1)]
        ge = np.unpackbits(bits, axis=1, bitorder="little")[:, :slots].astype(bool)
        contrib[multi] = np.where(found, ge.sum(axis=1) - ge[np.arange(len(multi)), c.held[multi]], 1)
        beyond[qi[multi][over]] = True
        if not (found | over).all():  # pragma: no cover
            raise RuntimeError("internal error: a multi-image record is missing")
    resolved = np.minimum(1.0 + np.add.reduceat(contrib, seg), cap + 1)
    out["image-baseline"]["rank"][c.own] = np.where(finite, np.where(beyond, cap + 1, resolved), np.inf)
    out["image-baseline"]["image"][c.own] = img_top


def score_block(ent: dict[str, np.ndarray], blk: int, sd: SplitData, lay: Layout, pas: PassResult,
                out: dict[str, dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Every method of ``METHOD_ORDER`` for the split's queries of one row block (package doc, step 5).

    ``out[key]`` holds ``rank``, ``place`` and ``image`` arrays over the split's queries (in
    place-index order); the block's part is written. Returns the queries' top raw score and
    the places whose weighted θ must be made exact before the outcomes can be trusted.
    """
    th_s = np.asarray(sd.thresholds["simple"], dtype=np.float64)[lay.places]
    th_w = np.asarray(sd.thresholds["weighted"], dtype=np.float64)[lay.places]
    c = candidates(ent, blk, sd, lay, pas, th_s, th_w)
    top = score_place_level(c, th_s, th_w, lay.places, out)
    score_image_level(c, top, pas.records, lay.slots, out)
    return top, near_tie_places(c, th_w, sd.uncertainty)


def score_splits(entries: Entries, data: list[SplitData], lay: Layout, pas: PassResult, d: np.ndarray,
                 sums: FullSums, progress: Callable[[int, str], None] | None,
                 ) -> tuple[list[dict[str, dict[str, np.ndarray]]], list[np.ndarray]]:
    """Steps 5 and 6: every split scored block by block, near ties made exact and scored again.

    Where a block's outcomes of a split hang on a near tie, the places involved get their
    float64 θ and that block of that split is scored again, until no near tie is left.
    ``progress(row blocks done, message)`` after each row block of the first round.

    Returns:
        Per split, the ``out`` of ``score_block`` over all its queries, and their top raw scores.
    """
    n_p = len(lay.places)
    outs = [{k: {"rank": np.empty(n_p), "place": np.empty(n_p, np.int64), "image": np.empty(n_p, np.int64)}
             for k in METHOD_ORDER} for _ in data]
    tops = [np.empty(n_p) for _ in data]
    todo = {blk: list(range(len(data))) for blk in range(lay.n_blocks)}  # row block -> splits to score
    first_round = True
    while todo:
        fixes: dict[int, dict[int, np.ndarray]] = {}  # split -> row block -> places to make exact
        for blk in sorted(todo):
            ent = entries.get(blk)
            for r in todo[blk]:
                tops[r][lay.place_range(blk)], fix = score_block(ent, blk, data[r], lay, pas, outs[r])
                if len(fix):
                    fixes.setdefault(r, {})[blk] = fix
            if progress and first_round:
                progress(blk + 1, f"scoring block {blk + 1}/{lay.n_blocks}")
        first_round = False
        todo = {}
        for r, by_block in sorted(fixes.items()):
            if not make_exact(data[r], np.unique(np.concatenate(list(by_block.values()))), d, lay, sums):
                # pragma: no cover - every doubtful comparison involves a place not yet exact
                raise RuntimeError("internal error: near ties did not resolve")
            for blk in by_block:
                todo.setdefault(blk, []).append(r)
    return outs, tops


def assemble(sd: SplitData, out: dict[str, dict[str, np.ndarray]], top: np.ndarray, b: np.ndarray,
             image_place: np.ndarray, image_traversal: np.ndarray, n_places: int) -> SplitScores:
    """The split's ``SplitScores`` as the reference has them, answers as positions in the training set.

    ``top`` and ``b`` are each query's top raw score and best correct score; the global θs
    follow from them and the place baseline.
    """
    sp = sd.split
    n_q = len(sp.queries)
    known = np.ones(n_q, dtype=bool)

    def outcome(key: str, rank, place, image) -> Outcome:
        pos = np.where(image >= 0, np.searchsorted(sp.train, np.maximum(image, 0)), -1)
        return Outcome(METHODS_BY_KEY[key], rank, place, pos, np.full(n_q, -1))

    img = out["image-baseline"]
    img["place"] = np.where(img["image"] >= 0, image_place[np.maximum(img["image"], 0)], -1)
    outcomes = {k: outcome(k, out[k]["rank"], out[k]["place"], out[k]["image"]) for k in METHOD_ORDER}
    base = out["place-baseline"]
    th = dict(sd.thresholds)

    def global_outcome(key: str, theta: float) -> Outcome:
        # the raw rule with one θ: the own place stays iff b ≥ θ, and then so does every
        # place above it, so the rank is the baseline's; the top answer stays iff it is ≥ θ
        rank = np.where(b >= theta, base["rank"], np.inf)
        acc = top >= theta
        return outcome(key, rank, np.where(acc, base["place"], -1), np.where(acc, base["image"], -1))

    outcomes["global-auto"] = global_outcome("global-auto", th["auto"])
    if "user" in th:
        outcomes["global-user"] = global_outcome("global-user", th["user"])
    th["oracle"] = oracle_global_threshold(top, outcomes["place-baseline"].rank == 1, known)
    outcomes["global-oracle"] = global_outcome("global-oracle", th["oracle"])
    empty = np.empty((0, n_places))
    return SplitScores(
        outcomes=outcomes, raw=empty, best=empty.astype(np.int64), correct=empty.astype(bool), known=known,
        query_traversal=image_traversal[sp.queries], train_traversal=image_traversal[sp.train],
        thresholds=th, spread=sd.spread, k_adaptive=sd.k_adaptive, top=top,
    )
