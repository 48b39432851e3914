"""Plotly figures of the explorer: pure functions, library results in, ``go.Figure`` out.

A leaf of the library (like LightGlue's ``viz2d``): nothing here computes a threshold or a
score, it only draws what ``method.database``, ``views.traversal`` and ``protocols.evaluation``
computed, so a test can read a figure's data and compare it with the library's numbers. No
streamlit import.

Conventions: vertical threshold lines are drawn as two-point scatter traces (not layout
shapes), so their ``x`` is in the figure's data; every trace that stands for a library
quantity has a ``name`` naming it (``"θ_p weighted"``, ``"raw_p"`` …) and, where a click
must select something, ``customdata`` carrying its id.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas  # noqa: F401  # imported before plotly: plotly.py#2433 (lazy-import race under threads)
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from vpr_explorer.protocols.evaluation import Evaluation
from vpr_explorer.protocols.precision_recall import PRCurve, PRPoint
from vpr_explorer.method.retrieval import METHODS_BY_KEY, QueryDecision
from vpr_explorer.method.stats import mixture_pdf
from vpr_explorer.settings import default_workers
from vpr_explorer.views.numbers import PlaceDetail, SimilarityGrid

KEPT = "#2e8b57"
DROPPED = "#c4c4c4"
SKIPPED = "#dcdcdc"
NEGATIVE = "#8c9eff"
POSITIVE = "#e4572e"
QUERY = "#f0a202"
BASELINE = "#6b6b6b"
REJECTED = "#e4572e"
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
LINE_COLOURS = {
    "θ_p simple": "#6a3d9a",
    "θ_p weighted": "#1f78b4",
    "θ_p(k)": "#e31a1c",
    "global θ, automatic": "#333333",
    "global θ, user value": "#b15928",
}
_MARGIN = dict(l=10, r=10, t=40, b=10)
#: Plotly's modebar sits over the top-right corner, where a subplot's title is: stood on its
#: side in a right margin of its own, it covers no title or data.
_SIDE_MODEBAR = dict(modebar=dict(orientation="v"), margin={**_MARGIN, "r": 40})
#: Two thresholds closer than this are equal (an ulp apart in exact arithmetic): named "=".
COINCIDENT = 1e-6
#: Two threshold lines closer than this share of the x range fall on the same pixels: named "≈".
NEAR_SHARE = 0.004
#: Height of one "drawn on one another" note above a plot area, in pixels.
NOTE_PX = 16


def _missing(x: float, fmt: str = ".3f") -> str:
    """``x`` formatted, or "—" for NaN/inf (a value with nothing behind it), never "nan" or "None"."""
    return f"{x:{fmt}}" if x is not None and np.isfinite(x) else "—"


def _note_coincident(fig: go.Figure, lines: Sequence[go.Scatter], span: float = 0.0) -> int:
    """Say which threshold lines are drawn on one another: in their legend names, hovers, and a note.

    Lines closer than ``NEAR_SHARE`` of the x ``span`` (or ``COINCIDENT``) fall on the same
    pixels whatever their dash, so each later one is named "(= θ …)" (equal) or "(≈ θ …)"
    (closer than a pixel) and the figure gets one note per group, values included. The notes
    stand above the plot area, one ``NOTE_PX`` row each, where no line reaches: the caller
    gives its top margin ``note_margin(returned count)``.

    Returns:
        How many notes were added.
    """
    near = max(COINCIDENT, NEAR_SHARE * span)
    names = [t.meta if isinstance(t.meta, str) else t.name for t in lines]
    groups: list[list[int]] = []
    for i, line in enumerate(lines):
        same = [j for j in range(i) if abs(line.x[0] - lines[j].x[0]) <= near]
        if same:
            marks = [("=" if abs(line.x[0] - lines[j].x[0]) <= COINCIDENT else "≈") + f" {names[j]}" for j in same]
            line.name = f"{line.name} ({', '.join(marks)}, drawn on it)"
            next(g for g in groups if same[0] in g).append(i)
        else:
            groups.append([i])
    notes = []
    for g in groups:
        if len(g) < 2:
            continue
        text = ", ".join(f"{names[i]} {lines[i].x[0]:.3f}" for i in g)
        for i in g:
            lines[i].hovertemplate = f"{text}<extra></extra>"
        notes.append(f"drawn on one another: {text}")
    for k, note in enumerate(notes):
        fig.add_annotation(text=note, xref="paper", yref="paper", x=0, y=1, yshift=NOTE_PX * (len(notes) - 1 - k),
                           xanchor="left", yanchor="bottom", showarrow=False, font=dict(size=11), name="coincident")
    return len(notes)


def note_margin(notes: int) -> dict:
    """``_MARGIN`` with room above the plot area for ``notes`` rows of ``_note_coincident``."""
    return {**_MARGIN, "t": _MARGIN["t"] + NOTE_PX * notes}


def _title(text: str) -> dict:
    """A figure title pinned to the top of the figure, so notes in a taller top margin stay below it."""
    return dict(text=text, y=1, yref="container", yanchor="top", pad=dict(t=10))


def _vline(name: str, x: float, y_top: float, *, dash: str = "solid", colour: str | None = None) -> go.Scatter:
    """A vertical line at ``x`` as a trace (so tests read its ``x``)."""
    return go.Scatter(
        x=[x, x], y=[0.0, y_top], mode="lines", name=f"{name} = {x:.3f}",
        line=dict(color=colour or LINE_COLOURS.get(name, "#444"), width=2, dash=dash),
        hovertemplate=f"{name} = {x:.4f}<extra></extra>", meta=name,
    )


def place_colours(place_ids: np.ndarray) -> list[str]:
    """A colour per place id (cycling), grey for ``-1``."""
    return [SKIPPED if p < 0 else PALETTE[int(p) % len(PALETTE)] for p in np.asarray(place_ids)]


# --------------------------------------------------------------------------- places


#: Frames a route strip shows at most (the first ones): enough to see group and step.
ROUTE_FRAMES_SHOWN = 600


def route_figure(
    frame_place: np.ndarray,
    traversals: Sequence[str],
    positions: np.ndarray | None = None,
    *,
    title: str = "",
    max_frames: int = ROUTE_FRAMES_SHOWN,
) -> go.Figure:
    """Each traversal as a strip of frames: place frames coloured by place, skipped frames grey.

    No legend: the x axis title says what the squares and grey ticks are (a legend under the
    strips would sit on that title).

    Args:
        frame_place: ``(n_frames,)`` place of each frame, ``-1`` where skipped.
        traversals: traversal names (one strip each; frame ``f`` is the same spot in all).
        positions: optional ``(n_frames, 2)`` route map; drawn beside the strips.
        max_frames: longer routes show their first ``max_frames`` frames (enough to see
            group and step) and say so in the title; the map is thinned to as many points.
    """
    frame_place = np.asarray(frame_place)
    n_frames = len(frame_place)
    if n_frames > max_frames:
        title = f"{title + ': ' if title else ''}frames 0–{max_frames - 1} of {n_frames:,} shown"
        if positions is not None:
            keep = np.unique(np.linspace(0, n_frames - 1, max_frames).round().astype(np.int64))
            positions, map_place, map_frames = np.asarray(positions)[keep], frame_place[keep], keep
        frame_place = frame_place[:max_frames]
    elif positions is not None:
        map_place, map_frames = frame_place, np.arange(n_frames)
    frames = np.arange(len(frame_place))
    inside = frame_place >= 0
    has_map = positions is not None
    fig = make_subplots(rows=1, cols=2 if has_map else 1, column_widths=[0.65, 0.35] if has_map else None,
                        subplot_titles=("frames per traversal", "route map") if has_map else None,
                        horizontal_spacing=0.06)
    for t in traversals:
        fig.add_trace(go.Scatter(
            x=frames[~inside], y=[t] * int((~inside).sum()), mode="markers", name="skipped frames",
            legendgroup="skipped", showlegend=False,
            marker=dict(symbol="line-ns-open", size=14, color=SKIPPED, line=dict(width=2, color=SKIPPED)),
            hovertemplate="frame %{x}: skipped<extra></extra>", meta=f"skipped {t}",
        ), row=1, col=1)
        fig.add_trace(go.Scatter(
            # No legend entry: a swatch shows one colour, these squares one per place (the axis title says so).
            x=frames[inside], y=[t] * int(inside.sum()), mode="markers", name="place frames",
            legendgroup="places", showlegend=False, customdata=frame_place[inside],
            marker=dict(symbol="square", size=9, color=place_colours(frame_place[inside])),
            hovertemplate="frame %{x}: P%{customdata}<extra></extra>", meta=f"places {t}",
        ), row=1, col=1)
    fig.update_xaxes(title_text="frame · squares: place frames, one colour per place (colours repeat)<br>"
                                "grey ticks: skipped frames", row=1, col=1)
    fig.update_yaxes(type="category", row=1, col=1)
    if has_map:
        xy = np.asarray(positions)
        fig.add_trace(go.Scatter(x=xy[:, 0], y=xy[:, 1], mode="lines", line=dict(color=SKIPPED, width=6),
                                 name="route", showlegend=False, hoverinfo="skip", meta="route"), row=1, col=2)
        on = map_place >= 0
        fig.add_trace(go.Scatter(
            x=xy[on, 0], y=xy[on, 1], mode="markers", name="place frames (map)", showlegend=False,
            customdata=np.stack([map_frames[on], map_place[on]], axis=1),
            marker=dict(size=7, color=place_colours(map_place[on])),
            hovertemplate="frame %{customdata[0]}: P%{customdata[1]}<extra></extra>", meta="map places",
        ), row=1, col=2)
        fig.update_xaxes(showticklabels=False, row=1, col=2)
        fig.update_yaxes(showticklabels=False, scaleanchor="x2", row=1, col=2)
    fig.update_layout(title=title or None, height=max(160 + 45 * len(traversals), 340 if has_map else 0),
                      showlegend=False, **_SIDE_MODEBAR)
    return fig


def theta_histogram(theta: Mapping[str, np.ndarray], auto: float, user_theta: float | None = None) -> go.Figure:
    """Histogram of θ_p over places for each variant, with the global thresholds as lines."""
    fig = go.Figure()
    values = [np.asarray(v, dtype=float) for v in theta.values()]
    for name, v in theta.items():
        v = np.asarray(v, dtype=float)
        fig.add_trace(go.Histogram(x=v[np.isfinite(v)], name=f"θ_p {name}", opacity=0.6, nbinsx=30,
                                   marker_color=LINE_COLOURS.get(f"θ_p {name}"), meta=f"θ_p {name}"))
    def peak(v: np.ndarray) -> int:
        v = v[np.isfinite(v)]
        # θ_p that are equal in exact arithmetic can differ by an ulp: numpy refuses 30 bins over that range
        flat = np.ptp(v) <= 1e-9 * max(1.0, float(np.abs(v).max()))
        return int(np.histogram(v, bins=1 if flat else 30)[0].max())

    counts = max((peak(v) for v in values if np.isfinite(v).any()), default=1)
    lines = [_vline("global θ, automatic", auto, float(counts), dash="dot")]
    if user_theta is not None:
        lines.append(_vline("global θ, user value", user_theta, float(counts), dash="dash"))
    fig.add_traces(lines)
    xs = np.r_[np.concatenate(values), auto, user_theta if user_theta is not None else auto]
    xs = xs[np.isfinite(xs)]
    notes = _note_coincident(fig, list(fig.data[-len(lines):]), float(np.ptp(xs)) if xs.size else 0.0)
    finite = [v[np.isfinite(v)] for v in values]
    if len(finite) == 2 and len(finite[0]) == len(finite[1]) and np.allclose(finite[0], finite[1], rtol=0,
                                                                             atol=COINCIDENT):
        fig.add_annotation(text=f"{' and '.join(f'θ_p {n}' for n in theta)} are equal at every place: "
                                "one histogram hides the other", xref="paper", yref="paper", x=0, y=1,
                           xanchor="left", yanchor="top", showarrow=False, font=dict(size=11),
                           bgcolor="rgba(255,255,255,0.8)")
    fig.update_layout(barmode="overlay", title=_title("θ_p of every place"), xaxis_title="similarity",
                      yaxis_title="places", height=320 + NOTE_PX * notes, margin=note_margin(notes),
                      legend=dict(orientation="h", y=-0.3))
    return fig


def recall_bars(recall1: Mapping[str, float], *, rejected: Mapping[str, float] | None = None,
                title: str = "Recall@1 of the query traversal") -> go.Figure:
    """One bar per method: Recall@1 (and, when given, the share rejected as a second bar)."""
    keys = list(recall1)
    labels = [METHODS_BY_KEY[k].label for k in keys]
    # One colour per trace: the legend's swatch is then the colour of every bar it names.
    fig = go.Figure(go.Bar(x=labels, y=[recall1[k] for k in keys], name="Recall@1", customdata=keys,
                           marker_color=KEPT, text=[_missing(recall1[k], ".0%") for k in keys],
                           textposition="outside", meta="recall1"))
    if rejected is not None:
        fig.add_trace(go.Bar(x=labels, y=[rejected[k] for k in keys], name="rejected", customdata=keys,
                             marker_color=REJECTED, opacity=0.6, meta="rejected"))
    fig.update_layout(title=title, yaxis=dict(range=[0, 1.12], tickformat=".0%"), height=320, margin=_MARGIN,
                      barmode="group", legend=dict(orientation="h", y=-0.45))
    return fig


# --------------------------------------------------------------------------- thresholds


#: Above this many places the overview drops its place labels and draws smaller dots: a
#: sorted curve of θ_p is what stays readable (Nordland 64x32 has 358 places).
OVERVIEW_LABELLED_PLACES = 60
#: Above this many places the overview is drawn for the browser to redraw nothing on a pick:
#: θ_p as WebGL dots (``Scattergl``), μ⁺ and μ⁻ as one line each, and no mark of the selected
#: place (the page shows it beside the figure). Thousands of SVG points and columns take the
#: browser seconds to redraw on every pick (Nordland 64x32 at group 1, step 1: 3,576 places).
OVERVIEW_WEBGL_PLACES = 1000


def places_overview(theta: np.ndarray, positive_mean: np.ndarray, negative_mean: np.ndarray,
                    selected: int | None = None) -> go.Figure:
    """Every place sorted by θ_p, as dots, with its mean negative and mean same-place score; click a place to pick it.

    Dots, not bars: the similarities sit far from zero, so a bar cut off at the axis floor
    would show lengths that mean nothing. The θ_p dots (``meta="theta"``) carry
    ``customdata`` = place id, in sorted order; behind them one column per place
    (``meta="pick"``, transparent but for the selected place's tint) spans the plot, so a
    click anywhere above a place picks it. Above ``OVERVIEW_LABELLED_PLACES`` places the
    x axis is the rank by θ_p (hover names the place). Above ``OVERVIEW_WEBGL_PLACES``
    (``overview_many``) the figure does not depend on ``selected``. Places are named
    ``P<id>``, as everywhere in the app.
    """
    theta = np.asarray(theta, dtype=float)
    order = np.argsort(theta, kind="stable")
    order = order[np.isfinite(theta[order])]
    pos = np.asarray(positive_mean, dtype=float)[order]
    neg = np.asarray(negative_mean, dtype=float)[order]
    labelled = len(order) <= OVERVIEW_LABELLED_PLACES
    x = [f"P{p}" for p in order] if labelled else np.arange(len(order))
    size = 9 if labelled else 5
    lo = np.nanmin(np.r_[theta[order], neg]) if len(order) else 0.0
    hi = np.nanmax(np.r_[theta[order], pos]) if len(order) else 1.0
    pad = 0.05 * (hi - lo if hi > lo else 1.0)
    hover = [f"P{p}: θ_p {_missing(t)}, μ⁺ {_missing(a)}, μ⁻ {_missing(b)}"
             for p, t, a, b in zip(order, theta[order], pos, neg)]
    if len(order) > OVERVIEW_WEBGL_PLACES:
        return overview_many(theta[order], pos, neg, order, hover, (lo - pad, hi + pad))
    fig = go.Figure()
    fig.add_trace(go.Bar(
        x=x, y=np.full(len(order), hi - lo + 2 * pad), base=lo - pad, customdata=order.tolist(), meta="pick",
        name="pick", showlegend=False, text=hover, textposition="none", hovertemplate="%{text}<extra></extra>",
        marker=dict(color=["rgba(228,87,46,0.15)" if p == selected else "rgba(0,0,0,0)" for p in order],
                    line=dict(width=0)),
    ))
    fig.add_trace(go.Scatter(
        x=x, y=theta[order], customdata=order.tolist(), name="θ_p weighted", meta="theta",
        mode="markers" if labelled else "lines+markers", line=dict(color=LINE_COLOURS["θ_p weighted"], width=1),
        marker=dict(size=[size + 5 if p == selected else size for p in order],
                    color=[POSITIVE if p == selected else LINE_COLOURS["θ_p weighted"] for p in order]),
        text=hover, hovertemplate="%{text}<extra></extra>",
    ))
    fig.add_trace(go.Scatter(x=x, y=pos, mode="markers", name="mean same-place score μ⁺",
                             marker=dict(symbol="diamond", color=POSITIVE, size=size - 2),
                             customdata=order, meta="positive_mean", text=hover,
                             hovertemplate="%{text}<extra></extra>"))
    # θ_p is a weighted mean of the μᵢ, so it often sits on μ⁻: a wider ring stays visible around its dot.
    fig.add_trace(go.Scatter(x=x, y=neg, mode="markers", name="mixture mean μ⁻ (ring, often around θ_p)",
                             marker=dict(symbol="circle-open", color=NEGATIVE, size=size + (7 if labelled else 3),
                                         line=dict(width=2 if labelled else 1)),
                             customdata=order, meta="negative_mean", text=hover,
                             hovertemplate="%{text}<extra></extra>"))
    xaxis = (dict(title="place", type="category") if labelled else
             dict(title=f"the {len(order)} places, ranked by θ_p (hover for the place; click to pick it)",
                  range=[-1, len(order)]))
    fig.update_layout(title=f"All {len(order)} places, sorted by θ_p (click a place to pick it)", height=300,
                      yaxis=dict(range=[lo - pad, hi + pad], title="similarity"), xaxis=xaxis, bargap=0,
                      legend=dict(orientation="h", y=-0.35), hovermode="closest", **_SIDE_MODEBAR)
    return fig


def overview_many(theta: np.ndarray, positive_mean: np.ndarray, negative_mean: np.ndarray, order: np.ndarray,
                  hover: Sequence[str], y_range: tuple[float, float]) -> go.Figure:
    """``places_overview`` of more than ``OVERVIEW_WEBGL_PLACES`` places: the same figure whichever place is picked.

    Args:
        theta, positive_mean, negative_mean: ``(n,)`` in ascending θ_p order; order: ``(n,)``
            the place ids in that order; hover: ``(n,)`` each place's hover text; y_range: the
            similarity axis.
    """
    n = len(order)
    x = np.arange(n)
    fig = go.Figure()
    # a click selects a dot: the selection must not restyle the dots either
    fig.add_trace(go.Scattergl(
        x=x, y=theta, customdata=order.tolist(), name="θ_p weighted", meta="theta", mode="markers",
        marker=dict(size=5, color=LINE_COLOURS["θ_p weighted"]), selected=dict(marker=dict(opacity=1)),
        unselected=dict(marker=dict(opacity=1)), text=list(hover), hovertemplate="%{text}<extra></extra>",
    ))
    fig.add_trace(go.Scatter(x=x, y=positive_mean, mode="lines", name="mean same-place score μ⁺",
                             meta="positive_mean", line=dict(color=POSITIVE, width=1), opacity=0.6, hoverinfo="skip"))
    fig.add_trace(go.Scatter(x=x, y=negative_mean, mode="lines", name="mixture mean μ⁻", meta="negative_mean",
                             line=dict(color=NEGATIVE, width=2), hoverinfo="skip"))
    fig.update_layout(title=f"All {n} places, sorted by θ_p (click a θ_p dot to pick its place)", height=300,
                      xaxis=dict(title=f"the {n} places, ranked by θ_p (hover a dot for its place)", range=[-1, n]),
                      yaxis=dict(range=list(y_range), title="similarity"), legend=dict(orientation="h", y=-0.35),
                      hovermode="closest", **_SIDE_MODEBAR)
    return fig


def mixture_grid(detail: PlaceDetail, n: int = 400) -> np.ndarray:
    """The x values a mixture figure draws its curves on: covering negatives, positives and thresholds."""
    parts = (detail.negatives, detail.positives, detail.query_raw, list(detail.theta.values()), [detail.auto],
             detail.mu - 4 * detail.sigma, detail.mu + 4 * detail.sigma)
    lo, hi = np.inf, -np.inf
    for part in parts:  # each part's own range: a place of a million-image database has 10⁷ negatives
        a = np.asarray(part).ravel()  # in its own float dtype: no float64 copy of float32 scores
        if a.dtype.kind != "f":
            a = a.astype(np.float64)
        if a.size and not (np.isfinite(a.min()) and np.isfinite(a.max())):
            a = a[np.isfinite(a)]
        if a.size:
            lo, hi = min(lo, float(a.min())), max(hi, float(a.max()))
    if lo > hi:  # nothing finite to cover
        lo, hi = 0.0, 1.0
    pad = 0.03 * (hi - lo if hi > lo else 1.0)
    return np.linspace(lo - pad, hi + pad, n)


#: Bins of the negative-score histogram behind the mixture.
NEGATIVE_BINS = 60


#: values binned per thread by ``density_histogram`` (fewer are binned in one call)
HISTOGRAM_PART = 1 << 21
#: the most threads ``density_histogram`` bins parts in
HISTOGRAM_THREADS = 4


def density_histogram(values: np.ndarray, bins: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """``np.histogram(values, bins, range=(lo, hi), density=True)`` on float64 edges, in parts side by side.

    The edges are float64 whatever the values' dtype (beside float32 scores, Python floats
    would be taken as float32): the bins of the values' float64 copy, bit for bit. Each part's
    integer counts add exactly, and the density is numpy's ``n / width / n.sum()`` of them, so
    the result is the one call's for any number of parts (``tests/test_plots.py``); a place of a
    million-image database has 10⁷ negative scores.
    """
    edges_range = (np.float64(lo), np.float64(hi))
    parts = [values[i : i + HISTOGRAM_PART] for i in range(0, len(values), HISTOGRAM_PART)] or [values]

    def count(part: np.ndarray) -> np.ndarray:
        return np.histogram(part, bins=bins, range=edges_range)[0]

    if len(parts) > 1:
        with ThreadPoolExecutor(min(len(parts), default_workers(HISTOGRAM_THREADS))) as pool:
            counts = sum(pool.map(count, parts))
    else:
        counts = count(parts[0])
    edges = np.histogram_bin_edges(values[:0], bins=bins, range=edges_range)
    return counts / np.diff(edges).astype(float) / counts.sum(), edges


def mixture_figure(
    detail: PlaceDetail,
    *,
    k: float = 0.0,
    method: str = "weighted",
    user_theta: float | None = None,
    n: int = 400,
) -> go.Figure:
    """One place's negative Gaussian mixture with its scores and every threshold.

    Thin curves: each training image's component wᵢ·N(x; μᵢ, σᵢ²) (its share of the
    mixture); bold: the mixture M(p) = Σ wᵢ N(μᵢ, σᵢ²); light bars: the actual negative
    scores (density); rugs: the place's same-place database scores and the raw_p of the
    queries whose right places include it; vertical lines: θ_p simple, θ_p weighted, θ_p(k) of ``method``, the
    automatic global θ and the user's θ.
    """
    x = mixture_grid(detail, n)
    mixture = mixture_pdf(x, detail.mu, detail.sigma, detail.weight)
    fig = go.Figure()
    density = None
    if detail.negatives.size:
        # Binned here, not in the browser: a place of a 100k-image database has ~10⁶ negative scores.
        lo, hi = float(detail.negatives.min()), float(detail.negatives.max())  # float64 edges: density_histogram
        density, edges = density_histogram(detail.negatives, NEGATIVE_BINS, lo, hi if hi > lo else lo + 0.01)
        fig.add_trace(go.Bar(x=(edges[:-1] + edges[1:]) / 2, y=density, width=np.diff(edges),
                             customdata=np.stack([edges[:-1], edges[1:]], axis=1),
                             marker=dict(color=NEGATIVE, line=dict(width=0)), opacity=0.35,
                             name="negative scores s(i, j), j another place", meta="negatives",
                             hovertemplate="%{customdata[0]:.3f}–%{customdata[1]:.3f}: density %{y:.2f}<extra></extra>"))
    for i, (m, s, w) in enumerate(zip(detail.mu, detail.sigma, detail.weight)):
        fig.add_trace(go.Scatter(
            x=x, y=mixture_pdf(x, m[None], s[None], w[None]), mode="lines", line=dict(width=1, color="#5c6bc0"),
            name="component wᵢ·N(μᵢ, σᵢ²) per training image", legendgroup="components", showlegend=i == 0,
            hovertemplate=f"image {int(detail.images[i])}: μ={m:.3f}, σ={s:.3f}, w={w:.2f}<extra></extra>",
            meta=f"component {i}",
        ))
    fig.add_trace(go.Scatter(x=x, y=mixture, mode="lines", line=dict(width=4, color="#1a237e"),
                             name="mixture M(p)", meta="mixture"))
    peak = float(mixture.max())
    if density is not None:
        peak = max(peak, float(density.max()))
    top = max(peak, 1e-9) * 1.15
    rug_y = -0.06 * top
    if detail.positives.size:
        fig.add_trace(go.Scatter(x=detail.positives, y=np.full(detail.positives.size, rug_y), mode="markers",
                                 marker=dict(symbol="line-ns-open", size=16, color=POSITIVE, line=dict(width=2)),
                                 name="same-place scores (database pairs)", meta="positives",
                                 hovertemplate="same-place score %{x:.3f}<extra></extra>"))
    if detail.query_raw.size:
        fig.add_trace(go.Scatter(x=detail.query_raw, y=np.full(detail.query_raw.size, 2 * rug_y), mode="markers",
                                 marker=dict(symbol="triangle-up", size=10, color=QUERY),
                                 name="raw_p of the queries right in this place", meta="query_raw",
                                 customdata=detail.query_images,
                                 hovertemplate="query image %{customdata}: raw_p %{x:.3f}<extra></extra>"))
    lines = [_vline("θ_p simple", detail.theta["simple"], top, dash="dot"),
             _vline("θ_p weighted", detail.theta["weighted"], top),
             _vline("θ_p(k)", detail.theta_k(k, method), top, dash="dash"),
             _vline("global θ, automatic", detail.auto, top, dash="dashdot")]
    lines[2].name = f"θ_p(k={k:g}) {method} = {detail.theta_k(k, method):.3f}"
    if user_theta is not None:
        lines.append(_vline("global θ, user value", user_theta, top, dash="longdash"))
    fig.add_traces(lines)
    notes = _note_coincident(fig, list(fig.data[-len(lines):]), float(x[-1] - x[0]))
    # the rugs lie below zero: ticks only where a density can be
    fig.update_layout(
        title=_title(f"P{detail.place}: negative mixture, scores and thresholds"), barmode="overlay",
        xaxis_title="cosine similarity",
        yaxis=dict(title="density", range=[3 * rug_y, top], tickmode="array", tickvals=density_ticks(top)),
        height=460 + NOTE_PX * notes, margin=note_margin(notes), legend=dict(orientation="h", y=-0.2),
    )
    return fig


def density_ticks(top: float, n: int = 5) -> np.ndarray:
    """About ``n`` round tick values from 0 to ``top`` (steps of 1, 2 or 5 × 10ᵉ), never below 0."""
    if not np.isfinite(top) or top <= 0:
        return np.zeros(1)
    e = 10.0 ** math.floor(math.log10(top / n))
    step = next(m * e for m in (1, 2, 5, 10) if m * e >= top / n)
    return np.arange(int(math.floor(top / step + 1e-9)) + 1) * step


# --------------------------------------------------------------------------- query inspector


def candidate_bars(decision: QueryDecision, key: str, candidates: Sequence[int], *, title: str | None = None) -> go.Figure:
    """raw_p of the candidate places under one method, as dots: coloured kept/dropped, θ ticks, margins.

    Dots, not bars: raw_p sits far from zero (0.3–1), and bars cut off at the axis floor
    would show lengths that mean nothing. The dots (``meta="raw_p"``) carry ``customdata`` =
    place id; the θ ticks (``meta="theta"``) sit at the method's threshold of each
    candidate; the answer has a black outline and right places are starred. Labels: the
    margin raw_p − θ (raw_p without a threshold); "—" where there is no value. A label
    stands on the side of its dot away from the θ tick (below where θ is above raw_p),
    so no tick crosses it.
    """
    m = METHODS_BY_KEY[key]
    cands = np.asarray(candidates, dtype=np.int64)
    raw = decision.raw[cands]
    kept = decision.kept(key)[cands] if m.level == "place" else np.ones(len(cands), dtype=bool)
    answer = decision.answer(key)
    true = set(int(p) for p in decision.true_places)
    labels = [f"{'★ ' if p in true else ''}P{p}" for p in cands]
    theta = decision.thresholds[m.threshold][cands] if m.threshold else None
    text = ([_missing(r - t, "+.3f") for r, t in zip(raw, theta)] if theta is not None else
            [_missing(r) for r in raw])
    below = theta >= raw if theta is not None else np.zeros(len(cands), dtype=bool)  # NaN: above
    fig = go.Figure(go.Scatter(
        x=labels, y=raw, customdata=cands, name="raw_p", meta="raw_p", text=text, mode="markers+text",
        textposition=["bottom center" if b else "top center" for b in below], cliponaxis=False,
        textfont=dict(size=10),
        marker=dict(size=16, color=[KEPT if k else DROPPED for k in kept],
                    line=dict(color=["#000" if p == answer else "rgba(0,0,0,0)" for p in cands], width=3)),
        hovertemplate="P%{customdata}: raw_p %{y:.3f}, label %{text}<extra></extra>",
    ))
    if theta is not None:
        fig.add_trace(go.Scatter(x=labels, y=theta, mode="markers", name=f"θ ({m.threshold})", meta="theta",
                                 customdata=cands, marker=dict(symbol="line-ew-open", size=26, color="#d62728",
                                                               line=dict(width=3)),
                                 hovertemplate="P%{customdata}: θ %{y:.3f}<extra></extra>"))
    finite = np.r_[raw, theta if theta is not None else []]
    finite = finite[np.isfinite(finite)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    pad = 0.15 * (hi - lo if hi > lo else 0.1)
    fig.update_layout(title=title or m.label, height=300, margin=_MARGIN, showlegend=False,
                      yaxis=dict(range=[lo - (2 if below.any() else 1) * pad, hi + 2 * pad],
                                 title="raw_p (dots; red tick: θ)"),
                      xaxis=dict(type="category"))
    return fig


# --------------------------------------------------------------------------- evaluation


def recall_figure(ev: Evaluation) -> go.Figure:
    """Recall@K of every method as grouped bars (one group per method, one bar per K), ± std over runs.

    A protocol of one run (traversal, database/queries, or ``runs=1``) has no spread: its
    bars carry no error bars and its title says "one run".
    """
    fig = go.Figure()
    labels = [r.label for r in ev.rows]
    runs = ev.settings.get("runs")
    several = isinstance(runs, (int, np.integer)) and not isinstance(runs, bool) and runs > 1
    for k in ev.ks:
        fig.add_trace(go.Bar(
            x=labels, y=[r.recall[k][0] for r in ev.rows], name=f"R@{k}", meta=f"R@{k}",
            customdata=[r.key for r in ev.rows],
            error_y=dict(type="data", array=[0.0 if math.isnan(r.recall[k][1]) else r.recall[k][1] for r in ev.rows],
                         visible=several),
        ))
    title = f"Recall@K (mean ± std over {runs} runs)" if several else "Recall@K (one run)"
    fig.update_layout(barmode="group", title=title, yaxis=dict(range=[0, 1.05],
                      tickformat=".0%"), height=380, margin=_MARGIN, legend=dict(orientation="h", y=-0.35))
    return fig


def tradeoff_figure(ev: Evaluation, rule: str = "margin") -> go.Figure:
    """Open-set trade-off: unknown-place rejection (x) against known-place Recall@1 (y).

    One line per θ_p(k) family (``rule``), k = 0 (the paper) marked with a large symbol,
    adaptive k as a diamond, the global θ sweep as a grey line, the automatic and oracle
    global θ as stars, named with their θ (the mean of the runs' θ, three decimals; a θ above 1
    says it accepts no query).
    """
    fig = go.Figure()
    colours = {"θ_p(k) simple": LINE_COLOURS["θ_p simple"], "θ_p(k) weighted": LINE_COLOURS["θ_p weighted"]}
    for series, colour in colours.items():
        pts = [t for t in ev.tradeoff if t.series == series and t.rule == rule]
        if not pts:
            continue
        fig.add_trace(go.Scatter(
            x=[t.unknown_rejection[0] for t in pts], y=[t.known_recall1[0] for t in pts], mode="lines+markers",
            name=f"{series} ({rule})", meta=series, customdata=[t.param for t in pts], line=dict(color=colour),
            text=[f"k={t.param:+g}, precision {t.precision[0]:.0%}" for t in pts],
            hovertemplate="%{text}<br>rejected %{x:.0%}, R@1 %{y:.0%}<extra></extra>",
        ))
        zero = [t for t in pts if t.param == 0.0]
        if zero:
            fig.add_trace(go.Scatter(x=[zero[0].unknown_rejection[0]], y=[zero[0].known_recall1[0]], mode="markers",
                                     marker=dict(size=16, symbol="circle-open", color=colour, line=dict(width=3)),
                                     name=f"k = 0 (paper), {series.split()[-1]}", meta=f"k0 {series}"))
        adaptive = [t for t in ev.tradeoff if t.series == f"adaptive k {series.split()[-1]}" and t.rule == rule]
        if adaptive:
            fig.add_trace(go.Scatter(x=[adaptive[0].unknown_rejection[0]], y=[adaptive[0].known_recall1[0]],
                                     mode="markers", marker=dict(size=12, symbol="diamond", color=colour),
                                     name=f"adaptive k, {series.split()[-1]}", meta=adaptive[0].series))
    sweep = [t for t in ev.tradeoff if t.series == "global θ"]
    if sweep:
        fig.add_trace(go.Scatter(
            x=[t.unknown_rejection[0] for t in sweep], y=[t.known_recall1[0] for t in sweep], mode="lines+markers",
            name="global θ sweep", meta="global θ", line=dict(color="#999", dash="dot"),
            customdata=[t.param for t in sweep], hovertemplate="θ=%{customdata:.3f}: rejected %{x:.0%}, R@1 %{y:.0%}<extra></extra>",
        ))
    runs = ev.settings.get("runs")
    mean = f": the mean over {runs} runs" if isinstance(runs, int) and runs > 1 else ""
    for series, symbol in (("global θ, automatic", "star"), ("global θ, oracle", "star-triangle-up")):
        pts = [t for t in ev.tradeoff if t.series == series]
        if pts:
            above = ", above 1: it accepts no query" if pts[0].param > 1 else ""  # 1: the largest similarity
            fig.add_trace(go.Scatter(x=[pts[0].unknown_rejection[0]], y=[pts[0].known_recall1[0]], mode="markers",
                                     marker=dict(size=14, symbol=symbol, color="#333"), meta=series,
                                     name=f"{series} (θ={pts[0].param:.3f}{mean}{above})"))
    fig.update_layout(title="Open set: unknown places rejected vs known-place Recall@1",
                      xaxis=dict(title="unknown-place queries rejected", tickformat=".0%", range=[-0.03, 1.03]),
                      yaxis=dict(title="known-place Recall@1", tickformat=".0%", range=[-0.03, 1.03]),
                      height=460, margin=_MARGIN, legend=dict(orientation="h", y=-0.25))
    return fig


def pr_figure(curves: Mapping[str, PRCurve], operating_points: Mapping[str, PRPoint], *,
              curve_of: Mapping[str, str] | None = None, title: str = "Precision–recall") -> go.Figure:
    """Precision (y) against recall (x): one line per curve, one marker per method at its own threshold.

    Curve traces (``meta`` = the curve's name) carry ``customdata`` = the θ or k of each
    point (``None`` at the start point, nothing accepted); their names give the AUC and the
    queries with no true match (unknown places: false positives when accepted). Operating points
    (``meta = "own <label>"``) take the colour of their curve when ``curve_of`` maps the
    label to it; a method that accepts no query has no precision, and its name says
    "accepts no query (P —, …)" as the tables' "—" does (its marker stays at the curves' start, P = 1).
    """
    fig = go.Figure()
    colours = {}
    for i, (name, c) in enumerate(curves.items()):
        colours[name] = PALETTE[i % len(PALETTE)]
        auc = "—" if math.isnan(c.auc) else f"{c.auc:.3f}"
        fig.add_trace(go.Scatter(
            x=c.recall, y=c.precision, mode="lines", meta=name,
            name=f"{name}: AUC {auc}, {c.n_unknown:,} of {c.n_known + c.n_unknown:,} queries with no true match",
            line=dict(color=colours[name], width=2),
            customdata=[float(t) if np.isfinite(t) else None for t in c.threshold],
            hovertemplate=(f"{c.param}=%{{customdata:.3f}}: recall %{{x:.1%}}, precision %{{y:.1%}}"
                           f"<extra>{name}</extra>"),
        ))
    for label, p in operating_points.items():
        colour = colours.get((curve_of or {}).get(label), "#333")
        # nothing accepted: no precision to give (the tables' "—"); the marker sits at the curves' start, P = 1
        said = (f"{label}: accepts no query (P —, R {p.recall:.0%})" if not p.accepted else
                f"{label}: P {p.precision:.0%}, R {p.recall:.0%}")
        fig.add_trace(go.Scatter(
            x=[p.recall], y=[p.precision], mode="markers", meta=f"own {label}", name=said,
            marker=dict(size=11, symbol="circle-open", color=colour, line=dict(width=3)),
            hovertemplate=(f"{label}: accepts no query, recall %{{x:.1%}}, precision —<extra></extra>"
                           if not p.accepted else
                           f"{label}: recall %{{x:.1%}}, precision %{{y:.1%}}<extra></extra>"),
        ))
    fig.update_layout(title=title, xaxis=dict(title="recall (of known-place queries)", tickformat=".0%",
                                              range=[-0.02, 1.02]),
                      yaxis=dict(title="precision of accepted top-1", tickformat=".0%", range=[-0.02, 1.04]),
                      height=460, margin=_MARGIN, legend=dict(orientation="h", y=-0.25))
    return fig


def evaluation_pr_figure(ev: Evaluation) -> go.Figure:
    """``pr_figure`` of an evaluation run with ``pr=True``: its curves and every method's own point."""
    return pr_figure(ev.pr_curves, {r.label: r.own for r in ev.pr}, curve_of={r.label: r.curve for r in ev.pr},
                     title="Precision–recall, pooled over runs")


def similarity_heatmap(grid: SimilarityGrid, *, query: str, database: Sequence[str],
                       marked: tuple[int, int] | None = None) -> go.Figure:
    """Queries × database images similarity (``numbers.similarity_grid``); a click selects the pair behind a cell.

    Plotly heatmaps emit no selection events in Streamlit (streamlit#8760), so an
    invisible marker sits on every cell (``meta="cells"``) with ``customdata`` =
    ``[query image, database image]``: clicking a cell selects its marker.
    """
    rows, cols = grid.z.shape
    fig = go.Figure(go.Heatmap(z=grid.z, x=grid.col_frames, y=grid.row_frames, colorscale="Viridis",
                               colorbar=dict(title="similarity<br>s(q, i)"), meta="similarity", hoverinfo="skip"))
    xx, yy = np.meshgrid(grid.col_frames, grid.row_frames)
    fig.add_trace(go.Scattergl(
        x=xx.ravel(), y=yy.ravel(), mode="markers", meta="cells",
        marker=dict(size=max(3, int(600 / max(rows, cols))), color="rgba(0,0,0,0)", symbol="square"),
        # Plain lists, not a typed array: the browser then hands each point's pair back as a list.
        customdata=np.stack([grid.query_image.ravel(), grid.db_image.ravel()], axis=1).tolist(),
        text=[f"{v:.3f}" for v in grid.z.ravel()],
        hovertemplate="query %{y}, database image %{x}: s = %{text}<br>click to inspect<extra></extra>",
        showlegend=False,
    ))
    if marked is not None:
        fig.add_trace(go.Scatter(x=[marked[1]], y=[marked[0]], mode="markers", meta="marked", showlegend=False,
                                 marker=dict(symbol="x-thin-open", size=14, color="#e4572e", line=dict(width=3)),
                                 hoverinfo="skip"))
    n_q, n_db = grid.n_queries, grid.n_database
    pooled = ("" if grid.block == grid.row_block == 1 else
              f" (each cell: one query × the best of {grid.block} database images)" if grid.sampled else
              f" (each cell: the best of {grid.row_block} queries × {grid.block} database images)")
    fig.update_layout(title=f"Similarity: {n_q:,} queries ({query}) × {n_db:,} database images{pooled}",
                      xaxis=dict(title=f"database image ({' + '.join(database)}, in database order)"),
                      yaxis=dict(title=f"query ({query})", autorange="reversed"),
                      height=560, margin=_MARGIN, dragmode="zoom")
    return fig


def selected_pair(point: Mapping) -> tuple[int, int] | None:
    """``(query image, database image)`` of a clicked ``similarity_heatmap`` cell, from a selection point.

    The point's ``customdata`` arrives as a list, or as an index-keyed dict when the
    figure was sent with typed arrays; ``None`` for a point without a pair.
    """
    data = point.get("customdata")
    if isinstance(data, Mapping):
        data = [data[k] for k in sorted(data, key=int)]
    if not isinstance(data, Sequence) or len(data) != 2:
        return None
    return int(data[0]), int(data[1])
