"""The map of a position-tagged dataset: database images coloured by place, queries, one query's radius.

A leaf beside ``plots``: Plotly figures from arrays, in plain metres (there are no map
tiles: the explorer runs without internet). Positions are UTM or any metric plane; the
axes count metres from a round origin below the lowest position (said in the axis titles),
with one metre the same length on both axes.

With a selected query the view opens on its neighbourhood (``neighbourhood``): the radius
circle is then tens of pixels wide, not a dot under the star; zooming out shows the rest.
``picked_query`` turns a click into a query: a click on a database dot that a query's cross
lies on (plotly hands the click to the dot, drawn first) selects the query nearest it.

Every trace carries a ``meta`` name, so that tests read it back from the figure's JSON:
``"database, between places"`` (grey), ``"database places"`` (coloured by place, ``text``
= place id), ``"queries"`` (thin crosses over them, ``customdata`` = query index, for clicks), and for the selected
query ``"selected query"``, ``"radius"`` (a circle of the positive radius), ``"positives"``
(its database images within the radius), ``"candidate places"`` (the database images of
the places it was compared with first) and ``"answer"`` (the place a method answered).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import plotly.graph_objects as go

from vpr_explorer.data.groundtruth import DEFAULT_RADIUS
from vpr_explorer.views.plots import PALETTE, SKIPPED

#: Above this many points a trace is drawn with WebGL (``Scattergl``): SVG slows down past a few thousand.
WEBGL_POINTS = 5_000
CIRCLE_POINTS = 73
#: The view around a selected query reaches this many radii from it (and its farthest positive)…
NEIGHBOURHOOD_RADII = 4.0
#: …and at least this many metres.
NEIGHBOURHOOD_MIN_M = 50.0
_MARGIN = dict(l=10, r=10, t=40, b=10)


def map_origin(*xy: np.ndarray | None) -> np.ndarray:
    """A round origin (a multiple of 100 m) at or below the lowest x and y of the positions given."""
    stacked = np.concatenate([np.asarray(a, dtype=np.float64).reshape(-1, 2) for a in xy if a is not None])
    return np.floor(stacked.min(axis=0) / 100.0) * 100.0


def circle(centre: Sequence[float], radius: float, n: int = CIRCLE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on a circle (the first repeated last), for a closed line."""
    t = np.linspace(0.0, 2.0 * math.pi, n)
    return centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)


def neighbourhood(centre: Sequence[float], radius: float | None, positives: np.ndarray | None = None
                  ) -> tuple[list[float], list[float]]:
    """The x and y ranges of the view around a selected query: a square about ``centre``.

    Its half side is ``NEIGHBOURHOOD_RADII`` radii, at least ``NEIGHBOURHOOD_MIN_M`` metres,
    and wide enough for every positive (``(n, 2)``, same frame as ``centre``) with a radius
    (at least a fifth of ``NEIGHBOURHOOD_MIN_M``) to spare. Plotly widens one of the ranges
    to the plot's shape (one metre is the same length on both axes).
    """
    c = np.asarray(centre, dtype=np.float64)
    r = float(radius) if radius is not None and np.isfinite(radius) and radius > 0 else 0.0
    half = max(NEIGHBOURHOOD_RADII * r, NEIGHBOURHOOD_MIN_M)
    pos = np.asarray(positives if positives is not None else np.zeros((0, 2)), dtype=np.float64).reshape(-1, 2)
    if len(pos):
        half = max(half, float(np.abs(pos - c).max()) + max(r, NEIGHBOURHOOD_MIN_M / 5))
    return [c[0] - half, c[0] + half], [c[1] - half, c[1] + half]


def picked_query(points: Sequence[Mapping], query_xy: np.ndarray, origin: Sequence[float],
                 near: float | None = None) -> int | None:
    """The query a click on ``layout_map`` selects, from Streamlit's selection ``points``.

    A point of the queries (or the selected query) carries its index as ``customdata``; any
    other point (a database dot, a ring) selects the query nearest its ``x``, ``y`` (metres
    from ``origin``) within ``near`` metres (default the field's 25 m radius), or nothing.

    Args:
        query_xy: ``(n_queries, 2)`` positions, in the dataset's frame (not less ``origin``).
    """
    for p in points:
        data = p.get("customdata")
        if isinstance(data, (int, float, np.integer, np.floating)) and not isinstance(data, bool):
            return int(data)
    q = np.asarray(query_xy, dtype=np.float64).reshape(-1, 2)
    limit = DEFAULT_RADIUS if near is None else float(near)
    for p in points:
        x, y = p.get("x"), p.get("y")
        if not isinstance(x, (int, float)) or not isinstance(y, (int, float)) or not len(q):
            continue
        dist = np.hypot(q[:, 0] - origin[0] - x, q[:, 1] - origin[1] - y)
        best = int(np.argmin(dist))  # the lowest index among equally near queries
        if dist[best] <= limit:
            return best
    return None


def _scatter(n: int):
    return go.Scattergl if n > WEBGL_POINTS else go.Scatter


def layout_map(
    database_xy: np.ndarray,
    database_place: np.ndarray,
    query_xy: np.ndarray,
    *,
    selected: int | None = None,
    radius: float | None = None,
    positives: Sequence[int] = (),
    candidates: Sequence[int] = (),
    answer: int | None = None,
    title: str | None = None,
    height: int | None = None,
) -> go.Figure:
    """Database images coloured by place (grey between places), queries as markers, one query highlighted.

    Args:
        database_xy: ``(n_database, 2)`` metres; query_xy: ``(n_queries, 2)``.
        database_place: ``(n_database,)`` place of each database image, ``-1`` between places.
        selected: a query index to highlight, with a circle of ``radius`` metres round it.
        positives: database positions right for the selected query (drawn as rings).
        candidates: place ids whose database images are outlined (the candidates it was compared with).
        answer: the place a method answered (outlined thicker), or ``None``.
        height: pixels; default from the positions' extent (a long thin route gets a low figure:
            one metre is the same length on both axes).

    With ``selected``, the axes' ranges are its ``neighbourhood`` (radius and positives).
    """
    db = np.asarray(database_xy, dtype=np.float64).reshape(-1, 2)
    q = np.asarray(query_xy, dtype=np.float64).reshape(-1, 2)
    place = np.asarray(database_place, dtype=np.int64)
    origin = map_origin(db, q)
    db_m, q_m = db - origin, q - origin
    if height is None:
        both = np.vstack([db_m, q_m])
        dx, dy = np.ptp(both[:, 0]) + 50.0, np.ptp(both[:, 1]) + 50.0
        height = int(np.clip(900.0 * dy / dx, 260.0, 640.0)) + 120  # ~900 px wide plot area, plus title and axis
    fig = go.Figure()
    out = place < 0
    trace = _scatter(int(out.sum()))
    fig.add_trace(trace(x=db_m[out, 0], y=db_m[out, 1], mode="markers", name="database, between places",
                        meta="database, between places", marker=dict(color=SKIPPED, size=5),
                        hovertemplate="database image between places<extra></extra>"))
    inside = ~out
    # the place's palette index as a number on a scale of the palette's colours: plotly checks a
    # numeric array at once, a list of 20,000 colour strings one by one (0.1 s a figure)
    last = len(PALETTE) - 1
    scale = [[k / last, c] for k, c in enumerate(PALETTE)]
    trace = _scatter(int(inside.sum()))
    fig.add_trace(trace(x=db_m[inside, 0], y=db_m[inside, 1], mode="markers", name="database, coloured by place",
                        meta="database places", text=[f"P{p}" for p in place[inside]],
                        marker=dict(color=place[inside] % len(PALETTE), colorscale=scale, cmin=0, cmax=last,
                                    showscale=False, size=7),
                        hovertemplate="database image of %{text}<extra></extra>"))
    trace = _scatter(len(q))  # thin crosses over the dots: queries often lie on the database
    fig.add_trace(trace(x=q_m[:, 0], y=q_m[:, 1], mode="markers", name="queries (click one)", meta="queries",
                        customdata=np.arange(len(q)),
                        marker=dict(symbol="x-thin", size=8, line=dict(width=1.2, color="rgba(30,30,30,0.45)")),
                        hovertemplate="query %{customdata}<extra></extra>"))
    if candidates is not None and len(candidates):
        mask = np.isin(place, np.asarray(candidates, dtype=np.int64))
        fig.add_trace(go.Scatter(x=db_m[mask, 0], y=db_m[mask, 1], mode="markers", name="candidate places",
                                 meta="candidate places", text=[f"P{p}" for p in place[mask]],
                                 marker=dict(size=12, color="rgba(0,0,0,0)", line=dict(color="#000", width=1.5)),
                                 hovertemplate="candidate %{text}<extra></extra>"))
    if answer is not None and answer >= 0:
        mask = place == answer
        fig.add_trace(go.Scatter(x=db_m[mask, 0], y=db_m[mask, 1], mode="markers", name=f"answer: P{answer}",
                                 meta="answer", marker=dict(size=16, color="rgba(0,0,0,0)",
                                                            line=dict(color="#d62728", width=3)),
                                 hovertemplate=f"answered place P{answer}<extra></extra>"))
    if selected is not None:
        pos = np.asarray(positives, dtype=np.int64)
        if len(pos):
            fig.add_trace(go.Scatter(x=db_m[pos, 0], y=db_m[pos, 1], mode="markers", name="its positives",
                                     meta="positives", text=[str(i) for i in pos],
                                     marker=dict(symbol="circle-open", size=14, color="#2ca02c", line=dict(width=2)),
                                     hovertemplate="positive: database image %{text}<extra></extra>"))
        if radius is not None:
            cx, cy = circle(q_m[selected], radius)
            fig.add_trace(go.Scatter(x=cx, y=cy, mode="lines", name=f"radius {radius:g} m", meta="radius",
                                     line=dict(color="#2ca02c", width=2, dash="dash"), hoverinfo="skip"))
        fig.add_trace(go.Scatter(x=[q_m[selected, 0]], y=[q_m[selected, 1]], mode="markers",
                                 name=f"query {selected}", meta="selected query", customdata=[selected],
                                 marker=dict(symbol="star", size=18, color="#ff7f0e", line=dict(color="#000", width=1)),
                                 hovertemplate="selected query %{customdata}<extra></extra>"))
    view = {}
    if selected is not None:
        pos = np.asarray(positives, dtype=np.int64)
        xr, yr = neighbourhood(q_m[selected], radius, db_m[pos] if len(pos) else None)
        view = dict(x=dict(range=xr), y=dict(range=yr))
    fig.update_layout(
        title=title or "Database images by place, and the queries (metres)", height=height, margin=_MARGIN,
        xaxis=dict(title=f"east (m from {origin[0]:,.0f})", zeroline=False, **view.get("x", {})),
        yaxis=dict(title=f"north (m from {origin[1]:,.0f})", zeroline=False, scaleanchor="x", scaleratio=1,
                   **view.get("y", {})),
        legend=dict(orientation="v", x=1.01, y=1.0, yanchor="top"), clickmode="event+select", dragmode="pan",
    )
    return fig
