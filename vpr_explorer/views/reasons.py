"""Why each acceptance rule accepted or rejected one query: a sentence with the rule's own numbers, and figures.

Reads an ``AcceptanceReport`` (``protocols.acceptance``) and explains its **closed set**
(the whole database) for one query q: per rule of ``RULES`` that ran, whether it accepted,
the image it answered (or weighed and rejected) and whether that image is right (the
value's ground truth), and one sentence with the numbers that decided it:

| rule | the sentence compares |
|---|---|
| ``baseline`` | nothing: it answers its most similar image, s₁ given |
| ``per-place``, ``per-place-k``, ``sequence-per-place`` | the answered (accepted) or best-scoring (rejected) place's score with its threshold |
| ``per-query`` | s_q with the smoothed threshold θ_q; the patch's KS test, and the boundary θ̂_q where bimodal, else where θ_q comes from |
| ``per-query-graph`` | the path's node cost 1 − s with C_nm = 1 − median θ_q (hidden at or above it) |
| ``seqslam`` | the uniqueness ratio with τ; the best trajectory's score and velocity, the best score outside the ratio window |
| ``top1-distance`` | d₁ with τ |
| ``pa-ratio`` | d₁/d₂ with τ |
| ``sue`` | SUE with τ |

A rule the bench left out gets "left out: " and the bench's reason. τ's origin is
``RuleDecisions.tau_note`` up to its colon ("oracle", "given"). Two numbers compared are
printed with the fewest decimals, from 3 (4 against a τ; for SUE's m², four significant digits
of the larger, no exponent) up to 7, that tell them apart, so a printed "≤" never sits
between two equal-looking numbers.
The comparison sign is the numbers' own (the rule's acceptance test applied to them), so it
agrees with the decision.

**The similarity rows.** Figures need the similarity matrix near q, and the bench does not
keep it: ``reason_rows`` gives the queries they read (the per-query patch's rows, q ± ds/2
of SeqSLAM, q ± ``GRAPH_HALF`` of the graph figure, cut to the queries) and
``neighbourhood`` computes those rows against every database image from the value's
descriptors (database rows first, then query rows): a few dozen rows, never the whole
matrix. It multiplies database × queries (``retrieval.similarity_t``: a few dozen query rows
against Nordland's 3,576 database images take 12 ms that way, 90 ms the other way round on
two cores), so its numbers may differ from the bench's matrix in the last float32 bits
(that function's note on BLAS kernels).
SeqSLAM's score matrix, which the bench does keep (``SeqSLAMResult.scores``), gives the
competing trajectory's image.

**Figures** (Plotly, the conventions of ``plots``: every trace that stands for a library
quantity has a ``meta`` name; vertical lines are two-point traces; heatmaps put database
images on x and queries on y, downwards, coloured Viridis):

* ``patch_figure``: the per-query patch ``QueryThresholds.patch_rows/patch_cols`` as a heatmap
  (``"patch"``, the best match ``"best match"``), and a density histogram of its values
  (``"values"``, ``HISTOGRAM_BINS`` bins) with the two fitted components πᵢN(μᵢ, σᵢ²)
  (``"component 0"``, ``"component 1"``, where bimodal), the boundary θ̂_q (``"boundary"``),
  the smoothed θ_q (``"threshold"``) and s_q (``"score"``);
* ``seqslam_figure``: queries q − ds/2 … q + ds/2 around the best trajectory (``"best
  trajectory"``; database image s + ⌊k·v⌋ at query q − ds/2 + k, s = match − ds/2,
  ``sequences.trajectory_offsets``) with the ratio window's edges (``"ratio window"``), and
  beside it the best-scoring trajectory farther than W/2 images from the match (``"competitor
  trajectory"``): the image of the lowest score outside the window in ``SeqSLAMResult.scores``
  (the lowest index on an exact tie), its velocity the one ``sequences.sequence_scores``
  picks for it on the ds + 1 rows (each row's contrast enhancement reads that row only, and
  the bench's shift by the whole matrix's minimum adds the same constant to every
  trajectory, so the choice is the bench's);
* ``graph_figure``: ``GraphMatch.path`` over queries q ± ``GRAPH_HALF`` (``"path"``), matched
  nodes (``"matched"``), hidden nodes (``"hidden"``) and the query's node (``"query node"``);
* ``nearest_two``: the PA-ratio's two nearest database images, s₁ ≥ s₂ and d = √(2 − 2s);
* ``sue_weights`` / ``sue_map``: the top-K database images (K = ``SUE_K``, the K largest
  similarities, an exact tie at the K-th to the lowest index), their softmax weights
  wᵢ ∝ exp(−slope·dᵢ) and SUE (``match_scores``' definition and defaults), drawn on
  ``maps.layout_map`` as markers sized by weight (``"top-K"``) with the weighted mean x̄
  (``"weighted mean"``).

Heatmaps show ``COLUMN_PAD`` database images either side of what they draw. No streamlit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import pandas  # noqa: F401  # imported before plotly: plotly.py#2433 (lazy-import race under threads)
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.graph_matcher import GraphMatch
from vpr_explorer.method.match_scores import SUE_CLIP_M, SUE_K, SUE_SLOPE, descriptor_distance
from vpr_explorer.method.query_threshold import QueryThresholds
from vpr_explorer.method.retrieval import TIE_TOLERANCE, similarity_t
from vpr_explorer.method.sequences import (
    CONTRAST_WINDOW,
    RATIO_WINDOW,
    VELOCITIES,
    SeqSLAMResult,
    sequence_scores,
    trajectory_offsets,
)
from vpr_explorer.method.stats import mixture_pdf
from vpr_explorer.protocols.acceptance import RULES, AcceptanceReport, Bench, PlaceScore, RuleDecisions
from vpr_explorer.views.maps import layout_map, map_origin
from vpr_explorer.views.plots import BASELINE, POSITIVE, QUERY, REJECTED

#: Queries either side of q that the graph matcher's figure shows.
GRAPH_HALF = 10
#: Database images either side of what a heatmap draws.
COLUMN_PAD = 5
#: Bins of the per-query patch's histogram.
HISTOGRAM_BINS = 30
#: Most decimals (or significant digits) a compared pair of numbers is printed with.
MAX_DIGITS = 7
_MARGIN = dict(l=10, r=10, t=60, b=10)
_COMPETITOR = "#d62728"
_PATH = "#ffffff"


class Status(StrEnum):
    """What a rule did with the query."""

    ACCEPTED = "accepted"
    REJECTED = "rejected"
    LEFT_OUT = "left out"


@dataclass(frozen=True)
class RuleReason:
    """One rule's decision on one query, in words.

    Attributes:
        key: the rule's key (``RULES``).
        label: the rule's name shown to people.
        status: accepted, rejected or left out.
        image: the database image it answered (accepted) or weighed and rejected (for the
            graph matcher the hidden node's image), ``-1`` where none.
        right: ``image`` is right for the query (ground truth); ``None`` where no image.
        sentence: the status, the image and the rule's own numbers.
    """

    key: str
    label: str
    status: Status
    image: int
    right: bool | None
    sentence: str

    @property
    def text(self) -> str:
        """``"<label>: <sentence>"``."""
        return f"{self.label}: {self.sentence}"


# --------------------------------------------------------------------------- numbers in words


def _pair(a: float, b: float, kind: str = "f", first: int | None = None) -> tuple[str, str]:
    """``a`` and ``b`` with the fewest decimals, from ``first`` up to ``MAX_DIGITS``, that tell them apart (module
    doc); "—" for NaN or infinity.

    ``kind="f"``: ``first`` defaults to 3 (a τ is given 4). ``kind="g"``: ``first`` gives the larger of the two
    four significant digits, written without an exponent and with thousands separators (SUE's m²).
    """
    if kind == "g":
        big = max((abs(x) for x in (a, b) if np.isfinite(x)), default=0.0)
        first = 3 - math.floor(math.log10(big)) if big > 0 else 3
        first = max(0, first)
    elif first is None:
        first = 3
    sep = "," if kind == "g" else ""
    for n in range(first, max(first, MAX_DIGITS) + 1):
        sa, sb = (f"{x:{sep}.{n}f}" if np.isfinite(x) else "—" for x in (a, b))
        if sa != sb or a == b:
            break
    return sa, sb


def _at_most(a: float, b: float) -> str:
    return "≤" if a <= b else ">"


def _at_least(a: float, b: float) -> str:
    return "≥" if a >= b else "<"


def _right(image: int, positives: np.ndarray) -> bool:
    return bool(np.isin(image, positives))


def _image(image: int, positives: np.ndarray) -> str:
    return f"image {image} ({'right' if _right(image, positives) else 'wrong'})"


def _tau(d: RuleDecisions) -> str:
    return d.tau_note.split(":")[0]


@dataclass(frozen=True, eq=False)
class _Query:
    """What every sentence reads of the query besides its rule's decisions."""

    index: int
    row: np.ndarray  # (n_database,) its similarities
    positives: np.ndarray  # its right database images
    settings: dict


def _head(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    """Status, image and the sentence's start ("accepted image 57 (right)")."""
    i = q.index
    if d.accepted[i]:
        image = int(d.answer[i])
        return Status.ACCEPTED, image, f"accepted {_image(image, q.positives)}"
    image = int(d.candidate[i])
    return Status.REJECTED, image, "rejected" + (f" {_image(image, q.positives)}" if image >= 0 else "")


def _baseline(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    return status, image, (f"{head}: no threshold, it answers its most similar database image "
                           f"(s₁ = {d.detail['score'][q.index]:.3f})")


def _places(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    i = q.index
    place, raw, theta = int(d.detail["place"][i]), float(d.detail["raw"][i]), float(d.detail["theta"][i])
    symbol = "θ_k" if d.rule.key == "per-place-k" else "θ_p"
    if d.rule.key == "sequence-per-place":
        score = "sequence score"
    elif q.settings.get("place_score") == PlaceScore.MEAN.value:
        score = "mean score"
    else:
        score = "raw_p"
    if place < 0:
        ends = " (one of the first or last ds/2 queries: no centred trajectory)" if d.rule.key == "sequence-per-place" else ""
        return status, image, f"{head}: no place has a score for this query{ends}"
    if not np.isfinite(theta):
        return status, image, f"{head}: its best place P{place} has no {symbol} (no training images)"
    sr, st = _pair(raw, theta)
    if status is Status.ACCEPTED:
        return status, image, (f"{head}: place P{place}'s {score} {sr} {_at_least(raw, theta)} its {symbol} {st}, "
                               "the best of the places at or above their threshold")
    return status, image, (f"{head}: no place reaches its threshold; the best, P{place}, has {score} {sr} "
                           f"{_at_least(raw, theta)} its {symbol} {st}")


def _measurement(qt: QueryThresholds, i: int) -> str:
    """Where θ_q comes from, and why the patch gave it (or gave no) measurement."""
    n, dks, crit = int(qt.n_values[i]), float(qt.ks_statistic[i]), float(qt.ks_critical[i])
    if qt.bimodal[i]:
        sd, sc = _pair(dks, crit)
        return f"patch bimodal, KS D {sd} > {sc}, boundary {qt.raw_threshold[i]:.3f}"
    if not np.isfinite(dks):
        why = f"patch of {n} value{'' if n == 1 else 's'} not tested"
    elif dks > crit:
        why = f"patch of {n} values found bimodal, KS D {dks:.3f} > {crit:.3f}, but too small for a mixture"
    else:
        sd, sc = _pair(dks, crit)
        why = f"patch unimodal, KS D {sd} ≤ {sc}"
    earlier = np.flatnonzero(qt.bimodal[:i + 1])
    if len(earlier):
        return f"{why}: no measurement, the threshold held since query {int(earlier[-1])}"
    return f"{why}: no measurement yet, the threshold is the patch mean {qt.patch_mean[i]:.3f}"


def _per_query(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    qt: QueryThresholds = d.result
    i = q.index
    s, t = float(qt.top_score[i]), float(qt.threshold[i])
    ss, st = _pair(s, t)
    return status, image, (f"{head}: its score {ss} {_at_least(s, t)} the smoothed threshold {st} "
                           f"({_measurement(qt, i)})")


def _graph(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    match: GraphMatch = d.result[0]
    i = q.index
    cost, cnm = float(match.node_cost[i]), float(match.non_matching_cost)
    sc, sn = _pair(cost, cnm)
    fanout = q.settings.get("fanout")
    why = f"C_nm {sn} (1 − the median per-query threshold {1 - cnm:.3f})"
    path = f"the cheapest path (fan-out {fanout})" if fanout is not None else "the cheapest path"
    if match.matched[i] >= 0:
        status, image, head = _head(d, q)
        return status, image, f"{head}: {path} passes it at cost 1 − s = {sc} < {why}"
    image = int(match.path[i])
    return Status.REJECTED, image, (f"rejected: {path} passes {_image(image, q.positives)} at cost 1 − s = {sc} "
                                    f"≥ {why}: a hidden node")


def _seqslam(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    res: SeqSLAMResult = d.result
    i = q.index
    if res.match[i] < 0:
        h = int(q.settings.get("ds", 10)) // 2
        return status, image, (f"{head}: no centred trajectory: SeqSLAM matches none of the first and last "
                               f"ds/2 = {h} queries")
    ratio = float(res.ratio[i])
    sr, st = _pair(ratio, d.tau, first=4)
    second = seqslam_competitor(res, i)
    other = "" if second is None else f", the best outside the ratio window (image {second[0]}) {second[1]:.4g}"
    return status, image, (f"{head}: uniqueness ratio {sr} {_at_most(ratio, d.tau)} τ {st} ({_tau(d)}): its best "
                           f"trajectory (velocity {res.velocity[i]:.1f}) scores {res.score[i]:.4g}{other}")


def _top1(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    x = float(d.detail["score"][q.index])
    sx, st = _pair(x, d.tau, first=4)
    return status, image, f"{head}: d₁ = {sx} {_at_most(x, d.tau)} τ {st} ({_tau(d)})"


def _pa_ratio(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    u = float(d.detail["score"][q.index])
    su, st = _pair(u, d.tau, first=4)
    two = nearest_two(q.row)
    if two.tie:
        return status, image, (f"{head}: its two nearest images tie (s₁ − s₂ ≤ {TIE_TOLERANCE:g}), so d₁/d₂ counts as "
                               f"{su} {_at_most(u, d.tau)} τ {st} ({_tau(d)})")
    if len(two.images) < 2:
        return status, image, f"{head}: no second image, d₁/d₂ = {su} {_at_most(u, d.tau)} τ {st} ({_tau(d)})"
    d1, d2 = two.distances
    return status, image, (f"{head}: d₁/d₂ = {d1:.3f}/{d2:.3f} = {su} {_at_most(u, d.tau)} τ {st} ({_tau(d)})")


def _sue(d: RuleDecisions, q: _Query) -> tuple[Status, int, str]:
    status, image, head = _head(d, q)
    x = float(d.detail["score"][q.index])
    sx, st = _pair(x, d.tau, "g")
    return status, image, (f"{head}: SUE {sx} m² {_at_most(x, d.tau)} τ {st} m² ({_tau(d)}), the weighted spread of "
                           f"its top-{SUE_K} database positions")


_SENTENCES = {
    "baseline": _baseline,
    "per-place": _places,
    "per-place-k": _places,
    "per-query": _per_query,
    "per-query-graph": _graph,
    "seqslam": _seqslam,
    "sequence-per-place": _places,
    "top1-distance": _top1,
    "pa-ratio": _pa_ratio,
    "sue": _sue,
}


def _check_query(report: AcceptanceReport, query: int) -> int:
    n = len(report.closed.genuine)
    if isinstance(query, bool) or not isinstance(query, (int, np.integer)) or not 0 <= query < n:
        raise VPRInputError(f"query={query!r}: the bench decided queries 0 to {n - 1}; choose one of them")
    return int(query)


def left_out_reason(report: AcceptanceReport, key: str) -> str:
    """Why the bench left rule ``key`` out (the report's note where it says more, e.g. SUE's positions)."""
    prefix = f"{key} left out: "
    note = next((n[len(prefix):] for n in report.notes if n.startswith(prefix)), None)
    return note or report.closed.left_out.get(key, "not run")


def rule_reasons(report: AcceptanceReport, query: int, row: np.ndarray,
                 positives: np.ndarray) -> tuple[RuleReason, ...]:
    """Each rule's decision on ``query`` in the closed set, in ``RULES`` order (module doc).

    Args:
        report: the bench on a dataset value.
        query: the query index.
        row: ``(n_database,)`` the query's similarities (``Neighbourhood.row``), for the PA-ratio's d₁ and d₂.
        positives: the query's right database images (the value's ``ground_truth.positives(query)``).
    Returns:
        One ``RuleReason`` per rule that ran or was left out (rules not asked for are skipped).
    Raises:
        VPRInputError: a query the bench did not decide, a row of another length.
    """
    i = _check_query(report, query)
    bench = report.closed
    r = np.asarray(row, dtype=np.float64)
    if r.shape != (len(bench.places),):
        raise VPRInputError(f"row of shape {r.shape}: the bench decided against {len(bench.places)} database "
                            "images; give the query's similarity to each")
    q = _Query(i, r, np.asarray(positives, dtype=np.int64).reshape(-1), dict(report.settings))
    out = []
    for rule in RULES:
        if rule.key in bench.decisions:
            status, image, sentence = _SENTENCES[rule.key](bench.decisions[rule.key], q)
            out.append(RuleReason(rule.key, rule.label, status, image,
                                  None if image < 0 else _right(image, q.positives), sentence))
        elif rule.key in bench.left_out:
            out.append(RuleReason(rule.key, rule.label, Status.LEFT_OUT, -1, None,
                                  f"left out: {left_out_reason(report, rule.key)}"))
    return tuple(out)


# --------------------------------------------------------------------------- the similarity near the query


@dataclass(frozen=True, eq=False)
class Neighbourhood:
    """Similarity rows of the queries ``first`` … ``first + len(similarity) − 1`` against every database image.

    Attributes:
        first: the first query.
        similarity: ``(n_rows, n_database)`` float32, read-only.
    """

    first: int
    similarity: np.ndarray

    def __post_init__(self) -> None:
        self.similarity.setflags(write=False)

    @property
    def stop(self) -> int:
        """One past the last query."""
        return self.first + len(self.similarity)

    def rows(self, start: int, stop: int) -> np.ndarray:
        """``(stop − start, n_database)`` the rows of queries ``start … stop − 1``.

        Raises:
            VPRInputError: a query outside the neighbourhood.
        """
        if not self.first <= start <= stop <= self.stop:
            raise VPRInputError(f"queries {start} to {stop - 1}: the neighbourhood holds {self.first} to "
                                f"{self.stop - 1}; compute it with reason_rows")
        return self.similarity[start - self.first:stop - self.first]

    def row(self, query: int) -> np.ndarray:
        """``(n_database,)`` the similarities of one query."""
        return self.rows(query, query + 1)[0]


def _query_thresholds(bench: Bench) -> QueryThresholds | None:
    if "per-query" in bench.decisions:
        return bench.decisions["per-query"].result
    if "per-query-graph" in bench.decisions:
        return bench.decisions["per-query-graph"].result[1]
    return None


def reason_rows(report: AcceptanceReport, query: int) -> tuple[int, int]:
    """The first and one-past-last query the figures of ``query`` read (module doc)."""
    i = _check_query(report, query)
    n = len(report.closed.genuine)
    reach = max(int(report.settings.get("ds", 0)) // 2, GRAPH_HALF)
    lo, hi = i - reach, i + reach + 1
    qt = _query_thresholds(report.closed)
    if qt is not None:
        lo, hi = min(lo, int(qt.patch_rows[i, 0])), max(hi, int(qt.patch_rows[i, 1]))
    return max(lo, 0), min(hi, n)


def neighbourhood(descriptors: np.ndarray, n_database: int, first: int, stop: int) -> Neighbourhood:
    """The similarity of queries ``first … stop − 1`` to every database image.

    Args:
        descriptors: ``(n_images, D)`` unit descriptors of the value, database rows first, then query rows.
        n_database: database images (the first rows).
        first, stop: the queries (``reason_rows``).
    Raises:
        VPRInputError: descriptors that are not 2-D, or queries outside the value.
    """
    d = np.asarray(descriptors)
    if d.ndim != 2 or not 0 < n_database < len(d):
        raise VPRInputError(f"descriptors of shape {d.shape} with {n_database} database rows: give (n_images, D) "
                            "descriptors, database rows first, then at least one query row")
    n_queries = len(d) - n_database
    if not 0 <= first < stop <= n_queries:
        raise VPRInputError(f"queries {first} to {stop - 1}: the value has queries 0 to {n_queries - 1}")
    rows = similarity_t(d[:n_database], d[n_database + first:n_database + stop])
    return Neighbourhood(first, np.ascontiguousarray(rows.T))


# --------------------------------------------------------------------------- figures


def _heatmap(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, *, meta: str = "similarity",
             showscale: bool = True) -> go.Heatmap:
    return go.Heatmap(z=z, x=cols, y=rows, coloraxis="coloraxis", meta=meta, showscale=showscale,
                      hovertemplate="query %{y}, database image %{x}: s = %{z:.3f}<extra></extra>")


def _columns(centre: np.ndarray, n_database: int, pad: int = COLUMN_PAD) -> np.ndarray:
    """Database images ``pad`` either side of the ones given, cut to the database."""
    lo, hi = max(0, int(np.min(centre)) - pad), min(n_database, int(np.max(centre)) + pad + 1)
    return np.arange(lo, hi)


def _vertical(name: str, meta: str, x: float, top: float, *, colour: str, dash: str = "solid") -> go.Scatter:
    return go.Scatter(x=[x, x], y=[0.0, top], mode="lines", name=f"{name} = {x:.3f}", meta=meta,
                      line=dict(color=colour, width=2, dash=dash), hovertemplate=f"{name} = {x:.4f}<extra></extra>")


def patch_figure(nb: Neighbourhood, qt: QueryThresholds, query: int) -> go.Figure:
    """The per-query patch as a heatmap, and its values' histogram with the mixture and thresholds (module doc)."""
    i = int(query)
    r0, r1 = (int(x) for x in qt.patch_rows[i])
    c0, c1 = (int(x) for x in qt.patch_cols[i])
    z = nb.rows(r0, r1)[:, c0:c1]
    values = z.astype(np.float64).ravel()
    m = int(qt.best_match[i])
    fig = make_subplots(rows=1, cols=2, column_widths=[0.4, 0.6], horizontal_spacing=0.18, subplot_titles=(
        f"patch: queries {r0}–{r1 - 1} × database {c0}–{c1 - 1}", f"its {len(values)} values"))
    fig.add_trace(_heatmap(z, np.arange(r0, r1), np.arange(c0, c1), meta="patch"), row=1, col=1)
    fig.add_trace(go.Scatter(x=[m], y=[i], mode="markers", meta="best match", name=f"query {i}, best match {m}",
                             marker=dict(symbol="x-thin-open", size=12, color=REJECTED, line=dict(width=3)),
                             hovertemplate=f"query {i}, its best match {m}<extra></extra>"), row=1, col=1)
    lines = [float(qt.threshold[i]), float(qt.top_score[i]), float(qt.raw_threshold[i]), *qt.means[i]]
    finite = [x for x in lines if np.isfinite(x)]
    lo, hi = min(values.min(), *finite), max(values.max(), *finite)
    density, edges = np.histogram(values, bins=HISTOGRAM_BINS, range=(float(values.min()), float(values.max()))
                                  if values.max() > values.min() else (values.min() - 0.01, values.max() + 0.01),
                                  density=True)
    fig.add_trace(go.Bar(x=(edges[:-1] + edges[1:]) / 2, y=density, width=np.diff(edges), meta="values",
                         name="patch values (density)", marker=dict(color="#8c9eff", line=dict(width=0)),
                         opacity=0.6, hovertemplate="%{x:.3f}: density %{y:.2f}<extra></extra>"), row=1, col=2)
    top = float(density.max())
    if qt.bimodal[i]:
        x = np.linspace(lo - 0.02 * (hi - lo), hi + 0.02 * (hi - lo), 300)
        for k in range(2):
            w, mu, s = float(qt.weights[i, k]), float(qt.means[i, k]), float(qt.stds[i, k])
            y = mixture_pdf(x, np.array([mu]), np.array([s]), np.array([w]))
            top = max(top, float(y.max()))
            fig.add_trace(go.Scatter(x=x, y=y, mode="lines", meta=f"component {k}", line=dict(width=2),
                                     name=f"π{k}·N(μ{k}, σ{k}²): π = {w:.2f}, μ = {mu:.3f}, σ = {s:.3f}"),
                          row=1, col=2)
    top *= 1.1
    # the boundary after θ_q, dotted over it: the first measurement of a sequence is θ_q itself
    fig.add_trace(_vertical("smoothed θ_q", "threshold", float(qt.threshold[i]), top, colour="#1f78b4"), row=1, col=2)
    if np.isfinite(qt.raw_threshold[i]):
        fig.add_trace(_vertical("boundary θ̂_q", "boundary", float(qt.raw_threshold[i]), top, colour=BASELINE,
                                dash="dot"), row=1, col=2)
    fig.add_trace(_vertical("s_q", "score", float(qt.top_score[i]), top, colour=QUERY, dash="dash"), row=1, col=2)
    fig.update_yaxes(autorange="reversed", title_text="query", row=1, col=1)
    fig.update_xaxes(title_text="database image", row=1, col=1)
    fig.update_xaxes(title_text="cosine similarity", row=1, col=2)
    fig.update_yaxes(title_text="density", row=1, col=2)
    state = "bimodal: a mixture and a boundary" if qt.bimodal[i] else "not bimodal: no measurement"
    fig.update_layout(title=f"Per-query threshold of query {i}: the patch is {state}", height=420, margin=_MARGIN,
                      coloraxis=dict(colorscale="Viridis", colorbar=dict(title="s", x=0.34, len=0.9, thickness=12)),
                      legend=dict(orientation="h", y=-0.25), barmode="overlay")
    return fig


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One SeqSLAM trajectory of a query.

    Attributes:
        image: the database image it is reported at (its start + ds/2).
        score: its sequence score (lower is better).
        velocity: database images per query frame.
        rows: ``(ds + 1,)`` the queries it spans.
        columns: ``(ds + 1,)`` the database image at each.
    """

    image: int
    score: float
    velocity: float
    rows: np.ndarray
    columns: np.ndarray


def seqslam_competitor(res: SeqSLAMResult, query: int, ratio_window: int = RATIO_WINDOW) -> tuple[int, float] | None:
    """The image and score of the lowest sequence score farther than W/2 images from the match (the ratio's
    denominator; the lowest index on an exact tie), ``None`` for an unmatched query or none finite."""
    i, m = int(query), int(res.match[query])
    if m < 0:
        return None
    scores = np.array(res.scores[i], dtype=np.float64)
    scores[max(0, m - ratio_window // 2):m + ratio_window // 2 + 1] = np.inf
    j = int(np.argmin(scores))
    return (j, float(scores[j])) if np.isfinite(scores[j]) else None


def seqslam_trajectories(nb: Neighbourhood, res: SeqSLAMResult, query: int, *, ds: int,
                         velocities: tuple[float, ...] = VELOCITIES, contrast_window: int = CONTRAST_WINDOW,
                         ratio_window: int = RATIO_WINDOW) -> tuple[Trajectory, Trajectory | None]:
    """The best trajectory of ``query`` and the best competing one outside the ratio window (module doc).

    Args:
        nb: rows holding queries query − ds/2 … query + ds/2.
        res: SeqSLAM's result on the value (the bench's), run with these ``ds``, ``velocities``, windows.
    Raises:
        VPRInputError: an unmatched query (one of the ds/2 at either end), rows missing from ``nb``.
    """
    i, m, h = int(query), int(res.match[query]), ds // 2
    if m < 0:
        raise VPRInputError(f"query {i} has no centred trajectory: SeqSLAM matches none of the first and last "
                            f"ds/2 = {h} queries")
    offsets = trajectory_offsets(ds, velocities)
    v = np.asarray(velocities, dtype=np.float64)
    rows = np.arange(i - h, i + h + 1)
    k = int(np.argmin(np.abs(v - res.velocity[i])))
    best = Trajectory(m, float(res.score[i]), float(v[k]), rows, m - h + offsets[k])
    other = seqslam_competitor(res, i, ratio_window)
    if other is None:
        return best, None
    j, score = other
    block = 1.0 - nb.rows(i - h, i + h + 1).astype(np.float64)
    _, vel = sequence_scores(block, contrast_window=contrast_window, ds=ds, velocities=velocities)
    kj = int(vel[h, j])
    return best, Trajectory(j, score, float(v[kj]), rows, j - h + offsets[kj])


def seqslam_figure(nb: Neighbourhood, best: Trajectory, competitor: Trajectory | None, query: int, *,
                   ratio_window: int = RATIO_WINDOW) -> go.Figure:
    """The similarity around the best trajectory and around the best competitor outside the ratio window."""
    n_db = nb.similarity.shape[1]
    panels = [("best trajectory", best, POSITIVE)] + ([] if competitor is None else
                                                       [("competitor trajectory", competitor, _COMPETITOR)])
    titles = [f"best: image {best.image}, score {best.score:.4g}, v = {best.velocity:g}"]
    if competitor is not None:
        titles.append(f"best outside the ratio window: image {competitor.image}, score {competitor.score:.4g}, "
                      f"v = {competitor.velocity:g}")
    fig = make_subplots(rows=1, cols=len(panels), subplot_titles=titles, horizontal_spacing=0.08)
    rows = best.rows
    z_rows = nb.rows(int(rows[0]), int(rows[-1]) + 1)
    half = ratio_window // 2
    for c, (meta, t, colour) in enumerate(panels, start=1):
        around = [t.columns.min(), t.columns.max()] + ([best.image - half, best.image + half] if c == 1 else [])
        cols = _columns(np.array(around), n_db)
        fig.add_trace(_heatmap(z_rows[:, cols], rows, cols, showscale=c == 1), row=1, col=c)
        fig.add_trace(go.Scatter(x=t.columns, y=t.rows, mode="lines+markers", meta=meta, name=f"{meta} (image "
                                 f"{t.image}, v = {t.velocity:g})", line=dict(color=colour, width=3),
                                 marker=dict(size=7, color=colour),
                                 hovertemplate="query %{y}: database image %{x}<extra></extra>"), row=1, col=c)
        fig.update_yaxes(autorange="reversed", title_text="query" if c == 1 else None, row=1, col=c)
        fig.update_xaxes(title_text="database image", row=1, col=c)
    lo, hi = best.image - half - 0.5, best.image + half + 0.5
    fig.add_trace(go.Scatter(x=[lo, lo, None, hi, hi], y=[rows[0], rows[-1], None, rows[0], rows[-1]], mode="lines",
                             meta="ratio window", name=f"ratio window: images {best.image - half}–{best.image + half}",
                             line=dict(color="#ffffff", width=1.5, dash="dash"), hoverinfo="skip"), row=1, col=1)
    fig.add_trace(go.Scatter(x=[best.image], y=[query], mode="markers", meta="match", name=f"query {query}'s match",
                             marker=dict(symbol="star", size=14, color=QUERY, line=dict(color="#000", width=1)),
                             hoverinfo="skip"), row=1, col=1)
    ratio = "" if competitor is None or competitor.score == 0 else f": ratio {best.score / competitor.score:.3f}"
    fig.update_layout(title=f"SeqSLAM, query {query}{ratio} (similarity shown; SeqSLAM sums contrast-enhanced "
                            "differences along each trajectory)", height=420, margin=_MARGIN,
                      coloraxis=dict(colorscale="Viridis", colorbar=dict(title="s")),
                      legend=dict(orientation="h", y=-0.2))
    return fig


def graph_figure(nb: Neighbourhood, match: GraphMatch, query: int, half: int = GRAPH_HALF) -> go.Figure:
    """The graph matcher's path over queries ``query ± half`` on the similarity, hidden nodes marked."""
    i = int(query)
    r0, r1 = max(nb.first, i - half), min(nb.stop, i + half + 1)
    rows = np.arange(r0, r1)
    path = np.asarray(match.path[r0:r1])
    hidden = np.asarray(match.hidden[r0:r1])
    cols = _columns(path, nb.similarity.shape[1])
    fig = go.Figure(_heatmap(nb.rows(r0, r1)[:, cols], rows, cols))
    fig.add_trace(go.Scatter(x=path, y=rows, mode="lines", meta="path", name="the cheapest path",
                             line=dict(color=_PATH, width=2), hoverinfo="skip"))
    for meta, keep, marker in (("matched", ~hidden, dict(symbol="circle", size=8, color=POSITIVE)),
                               ("hidden", hidden, dict(symbol="x", size=9, color=BASELINE,
                                                       line=dict(color="#ffffff", width=1)))):
        fig.add_trace(go.Scatter(x=path[keep], y=rows[keep], mode="markers", meta=meta, marker=marker,
                                 name=f"{meta} nodes (cost {'<' if meta == 'matched' else '≥'} C_nm "
                                      f"{match.non_matching_cost:.3f})",
                                 customdata=np.asarray(match.node_cost[r0:r1])[keep],
                                 hovertemplate="query %{y}: database image %{x}, cost %{customdata:.3f}<extra></extra>"))
    fig.add_trace(go.Scatter(x=[int(match.path[i])], y=[i], mode="markers", meta="query node",
                             name=f"query {i}'s node", hoverinfo="skip",
                             marker=dict(symbol="star", size=16, color=QUERY, line=dict(color="#000", width=1))))
    fig.update_layout(title=f"Graph matcher, queries {r0}–{r1 - 1}: the path, hidden nodes crossed", height=460,
                      margin=_MARGIN, coloraxis=dict(colorscale="Viridis", colorbar=dict(title="s")),
                      xaxis=dict(title="database image"), yaxis=dict(title="query", autorange="reversed"),
                      legend=dict(orientation="h", y=-0.2))
    return fig


@dataclass(frozen=True, eq=False)
class NearestTwo:
    """A query's two nearest database images (the PA-ratio's d₁ and d₂).

    Attributes:
        images: ``(2,)`` the images of the two largest similarities (fewer for a smaller database),
            in order, an exact tie to the lower index.
        similarities: ``(2,)`` s₁ ≥ s₂.
        distances: ``(2,)`` d = √(2 − 2s).
        tie: s₁ − s₂ ≤ ``TIE_TOLERANCE`` (the PA-ratio is then 1).
    """

    images: np.ndarray
    similarities: np.ndarray
    distances: np.ndarray
    tie: bool


def nearest_two(row: np.ndarray) -> NearestTwo:
    """The two nearest database images of one query's similarities ``(n_database,)``."""
    r = np.asarray(row, dtype=np.float64)
    order = np.argsort(-r, kind="stable")[:2]
    s = r[order]
    return NearestTwo(order, s, descriptor_distance(s), bool(len(s) == 2 and s[0] - s[1] <= TIE_TOLERANCE))


@dataclass(frozen=True, eq=False)
class SUEWeights:
    """SUE's top-K of one query (``match_scores.sue``'s definition).

    Attributes:
        images: ``(K,)`` the K nearest database images, nearest first.
        weights: ``(K,)`` their softmax weights, summing to 1.
        distances: ``(K,)`` their descriptor distances.
        centre: ``(2,)`` the weighted mean position x̄.
        score: SUE.
    """

    images: np.ndarray
    weights: np.ndarray
    distances: np.ndarray
    centre: np.ndarray
    score: float


def sue_weights(row: np.ndarray, database_xy: np.ndarray, *, k: int = SUE_K, slope: float = SUE_SLOPE,
                clip_m: float | None = SUE_CLIP_M) -> SUEWeights:
    """The top-K images of one query, their weights wᵢ ∝ exp(−slope·dᵢ), x̄ and SUE (module doc).

    Args:
        row: ``(n_database,)`` the query's similarities.
        database_xy: ``(n_database, 2)`` positions in metres.
    Raises:
        VPRInputError: positions of another shape or not finite.
    """
    r = np.asarray(row, dtype=np.float64)
    xy = np.asarray(database_xy, dtype=np.float64)
    if xy.shape != (len(r), 2) or not np.isfinite(xy).all():
        raise VPRInputError(f"database_xy of shape {xy.shape}: give ({len(r)}, 2) finite positions in metres")
    images = np.lexsort((np.arange(len(r)), -r))[:min(k, len(r))]
    d = descriptor_distance(r[images])
    e = np.exp(-slope * (d - d.min()))
    w = e / e.sum()
    rel = xy[images] - xy[images[0]]
    centre = rel.T @ w
    dev = rel - centre
    if clip_m is not None:
        dev = np.clip(dev, -clip_m, clip_m)
    return SUEWeights(images, w, d, xy[images[0]] + centre, float(0.5 * np.sum(w[:, None] * dev * dev)))


def sue_map(dataset: RetrievalDataset, places: np.ndarray, query: int, weights: SUEWeights) -> go.Figure:
    """``maps.layout_map`` of the value with the query's top-K images sized by their SUE weights, and x̄."""
    db = np.asarray(dataset.database_xy, dtype=np.float64)
    qxy = None if dataset.query_xy is None else np.asarray(dataset.query_xy, dtype=np.float64)
    fig = layout_map(db, places, np.empty((0, 2)) if qxy is None else qxy,
                     selected=None if qxy is None else int(query),
                     title=f"SUE of query {query}: its top-{len(weights.images)} database positions, sized by weight")
    origin = map_origin(db, qxy)
    at = db[weights.images] - origin
    fig.add_trace(go.Scatter(x=at[:, 0], y=at[:, 1], mode="markers", meta="top-K", name="top-K, sized by weight",
                             customdata=np.stack([weights.images, weights.weights], axis=1),
                             marker=dict(size=8 + 30 * weights.weights / weights.weights.max(), color=_COMPETITOR,
                                         opacity=0.6, line=dict(color="#000", width=1)),
                             hovertemplate="database image %{customdata[0]}: w = %{customdata[1]:.3f}<extra></extra>"))
    c = weights.centre - origin
    fig.add_trace(go.Scatter(x=[c[0]], y=[c[1]], mode="markers", meta="weighted mean", name="weighted mean x̄",
                             marker=dict(symbol="cross", size=14, color="#000"), hoverinfo="skip"))
    return fig
