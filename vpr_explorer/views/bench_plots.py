"""Plotly figures and the table of the acceptance bench (``protocols.acceptance``) and of discovered places.

A leaf like ``views.plots``: results in, ``go.Figure`` (or table rows) out, no streamlit.

* ``bench_rows``: the authors' table, one row per rule that ran (``RULES`` order): the
  closed set's F1, Recall@1 and Recall@5 with rejection, the natural open set's F1 and
  distractor rejection, the closed set's AUC-PR, and τ with where it came from;
  ``left_out_rows``: each rule that did not run, with the reason.
* ``bench_pr_figure``: every rule's precision–recall curve on one set (closed or natural
  open), each rule's own decisions marked as a point. The curves' recall is TP over the
  genuine queries (``PRCurve``); the point's is the same (``Counts.recall_all``), its
  precision TP/(TP+FP), and 1 where the rule accepts nothing (the curves' convention).
  The per-place rules' curves count a right *place*, their points a right *image*
  (the answer is the place's best image), so a point may sit off its curve.
* ``tutorial_pr_figure``: VPR_Tutorial's single-best-match and multi-match curves
  (``protocols.tutorial_pr``), named with the ground truth each counts.
* ``sweep_figure``: the bench swept over one parameter (``protocols.acceptance_sweep``): one
  line per rule across the parameter's values for one metric (``SWEEP_METRICS``: closed-set
  F1, natural open-set F1, distractor rejection), the values in increasing order; a rule the
  parameter does not affect (``sweep_affected``) is drawn faint and dashed. ``sweep_table``:
  the same numbers as rows (one per rule, one column per value); ``sweep_rows``: every number
  of the sweep, one row per rule and value (the CSV).
* ``discovery_figure``: the database route (x = database frame) with the group/step places
  and the discovered places as two band rows, place starts marked, and under it the online
  score against its threshold θ (``method.place_discovery.Discovery``).

Conventions are ``views.plots``': every trace standing for a library quantity has a
``meta`` naming it (a rule's key, ``"own <key>"``, ``"single"``, ``"score"`` …), so tests
read figures back and compare them with the library's numbers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pandas  # noqa: F401  # imported before plotly: plotly.py#2433 (lazy-import race under threads)
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.place_discovery import Discovery
from vpr_explorer.protocols.acceptance import RULES, RULES_BY_KEY, AcceptanceReport, Bench
from vpr_explorer.protocols.acceptance_sweep import BenchSweep, Parameter, SweepPoint
from vpr_explorer.protocols.tutorial_pr import TutorialPR
from vpr_explorer.views.plots import BASELINE, PALETTE, SKIPPED, place_colours

MARGIN = dict(l=10, r=10, t=40, b=10)
#: The set a figure or a column speaks of.
SETS = {"closed": "closed set", "natural": "natural open set"}
#: Colour of the discovered places' boundaries and the score line.
INK = "#333333"
THETA = "#e31a1c"


def _num(x) -> float:
    """``x`` as a float, NaN for ``None``."""
    return math.nan if x is None else float(x)


def rule_colours() -> dict[str, str]:
    """One colour per rule key: the image-level baseline grey, the others in ``PALETTE`` order."""
    others = [r.key for r in RULES if r.key != "baseline"]
    return {"baseline": BASELINE, **{k: PALETTE[i % len(PALETTE)] for i, k in enumerate(others)}}


# --------------------------------------------------------------------------- the table


def bench_rows(report: AcceptanceReport) -> list[dict]:
    """The authors' table: one dict per rule that ran on the closed set, in ``RULES`` order.

    Keys: ``key``, ``rule`` (label, "†" for an oracle τ), ``source``, ``closed F1``, ``R@1``,
    ``R@5`` (closed set, percent; NaN where 5 is not among the bench's K), ``open F1`` and
    ``rejection`` (natural open set, percent; NaN where it did not run or has no distractor),
    ``AUC-PR`` (closed set), ``τ`` (NaN for a rule with thresholds of its own) and ``τ from``.
    """
    rows = []
    closed, natural = report.closed, report.natural
    for rule in RULES:
        d = closed.decisions.get(rule.key)
        if d is None:
            continue
        c = closed.counts[rule.key]
        o = None if natural is None else natural.counts.get(rule.key)
        oracle = rule.free and d.tau_note.startswith("oracle")
        rows.append({
            "key": rule.key,
            "rule": rule.label + (" †" if oracle else ""),
            "source": rule.source,
            "closed F1": c.f1,
            "R@1": closed.recall[rule.key].get(1, math.nan),
            "R@5": closed.recall[rule.key].get(5, math.nan),
            "open F1": math.nan if o is None else o.f1,
            "rejection": math.nan if o is None else _num(o.rejection),
            "AUC-PR": float(d.curve.auc),
            "τ": float(d.tau),
            "τ from": d.tau_note,
        })
    return rows


def _reason(report: AcceptanceReport, key: str, why: str) -> str:
    """The report's own note for a rule left out (it may say more, e.g. why positions are not metres)."""
    prefix = f"{key} left out: "
    return next((n[len(prefix):] for n in report.notes if n.startswith(prefix)), why)


def left_out_rows(report: AcceptanceReport) -> list[dict]:
    """Each rule that did not run: ``key``, ``rule`` (label), ``where`` ("closed set", "natural open set" or
    "both sets") and ``reason``, in ``RULES`` order."""
    closed = report.closed.left_out
    natural = {} if report.natural is None else report.natural.left_out
    rows = []
    for rule in RULES:
        if rule.key not in closed and rule.key not in natural:
            continue
        both = rule.key in closed and (report.natural is None or rule.key in natural)
        where = "both sets" if both else SETS["closed"] if rule.key in closed else SETS["natural"]
        why = closed.get(rule.key) or natural[rule.key]
        rows.append({"key": rule.key, "rule": rule.label, "where": where, "reason": _reason(report, rule.key, why)})
    return rows


# --------------------------------------------------------------------------- precision–recall


def operating_point(bench: Bench, key: str) -> tuple[float, float]:
    """``(recall, precision)`` of a rule's own decisions, as fractions on its curve's axes (module doc)."""
    c = bench.counts[key]
    recall = c.tp / c.n_genuine if c.n_genuine else math.nan
    precision = c.tp / (c.tp + c.fp) if c.tp + c.fp else 1.0
    return recall, precision


def bench_pr_figure(bench: Bench, *, title: str) -> go.Figure:
    """Every rule's precision–recall curve of one set, and each rule's own decisions as a point.

    Curve traces: ``meta`` = the rule's key, ``customdata`` = the swept value of each point
    (``None`` at the start point, nothing accepted). Points: ``meta = "own <key>"``.
    """
    fig = go.Figure()
    colours = rule_colours()
    for key, d in bench.decisions.items():
        c = d.curve
        auc = "—" if not np.isfinite(c.auc) else f"{c.auc:.3f}"
        fig.add_trace(go.Scatter(
            x=c.recall, y=c.precision, mode="lines", meta=key, name=f"{d.rule.label}: AUC {auc}",
            legendgroup=key, line=dict(color=colours[key], width=2, dash="dash" if key == "baseline" else "solid"),
            customdata=[float(t) if np.isfinite(t) else None for t in c.threshold],
            hovertemplate=(f"{d.rule.sweep} = %{{customdata:.4g}}: recall %{{x:.1%}}, precision %{{y:.1%}}"
                           f"<extra>{d.rule.label}</extra>"),
        ))
    for key, d in bench.decisions.items():
        recall, precision = operating_point(bench, key)
        c = bench.counts[key]
        fig.add_trace(go.Scatter(
            x=[recall], y=[precision], mode="markers", meta=f"own {key}", legendgroup=key, showlegend=False,
            name=f"{d.rule.label}: its own decisions",
            marker=dict(size=11, symbol="circle-open", color=colours[key], line=dict(width=3)),
            hovertemplate=(f"{d.rule.label}, its own decisions: recall %{{x:.1%}}, precision %{{y:.1%}} "
                           f"(TP {c.tp}, FP {c.fp}, FN {c.fn}, TN {c.tn})<extra></extra>"),
        ))
    fig.update_layout(title=title, xaxis=dict(title="recall (TP / genuine queries)", tickformat=".0%",
                                              range=[-0.02, 1.02]),
                      yaxis=dict(title="precision (TP / accepted)", tickformat=".0%", range=[-0.02, 1.04]),
                      height=520, margin=MARGIN, legend=dict(orientation="h", y=-0.2))
    return fig


def tutorial_label(curve: TutorialPR) -> str:
    """What a VPR_Tutorial curve counts, e.g. "multi-match, soft positives ignored"."""
    what = "single-best-match" if curve.matching == "single" else "multi-match"
    truth = "soft positives ignored" if curve.soft_ignored else "hard ground truth only"
    return f"{what}, {truth}"


def tutorial_pr_figure(curves: Mapping[str, TutorialPR], *, title: str = "VPR_Tutorial precision–recall") -> go.Figure:
    """VPR_Tutorial's curves (``meta`` = the key given, e.g. ``"single"``, ``"multi"``), named with what they count."""
    fig = go.Figure()
    for i, (key, c) in enumerate(curves.items()):
        fig.add_trace(go.Scatter(
            x=c.recall, y=c.precision, mode="lines", meta=key, line=dict(color=PALETTE[i % len(PALETTE)], width=2),
            name=f"{tutorial_label(c)}: AUC {c.auc:.3f}, R@100P {c.recall_at_100_precision:.1%}",
            customdata=[None, *(float(t) for t in c.thresholds)],
            hovertemplate=(f"threshold %{{customdata:.4g}}: recall %{{x:.1%}}, precision %{{y:.1%}}"
                           f"<extra>{tutorial_label(c)}</extra>"),
        ))
    fig.update_layout(title=title, xaxis=dict(title="recall (TP / positives)", tickformat=".0%", range=[-0.02, 1.02]),
                      yaxis=dict(title="precision", tickformat=".0%", range=[-0.02, 1.04]),
                      height=360, margin=MARGIN, legend=dict(orientation="h", y=-0.3))
    return fig


# --------------------------------------------------------------------------- one parameter varied

#: metric key -> what a sweep figure or table shows of each rule at each value (percent)
SWEEP_METRICS = {"closed": "closed-set F1", "open": "natural open-set F1", "rejection": "rejection"}
#: how a rule the parameter does not affect is drawn: its numbers stand the same at every value
FAINT = 0.35


def sweep_value(point: SweepPoint, key: str, metric: str) -> float:
    """One rule's number at one value of a sweep, in percent: NaN where the rule did not run on that set (or, for
    rejection, the set has no distractor).

    Args:
        point: the bench at one value.
        key: a rule key.
        metric: a ``SWEEP_METRICS`` key.
    """
    if metric not in SWEEP_METRICS:
        raise VPRInputError(f"metric={metric!r}: choose one of {', '.join(SWEEP_METRICS)}")
    if metric == "closed":
        c = point.closed.counts.get(key)
        return math.nan if c is None else float(c.f1)
    o = None if point.natural is None else point.natural.counts.get(key)
    if o is None:
        return math.nan
    return float(o.f1) if metric == "open" else _num(o.rejection)


def sweep_keys(sweep: BenchSweep) -> list[str]:
    """The rules that ran at one value at least, in ``RULES`` order (the sweep's rows and lines)."""
    return [r.key for r in RULES if any(r.key in pt.closed.counts for pt in sweep.points)]


def sweep_affected(sweep: BenchSweep, metric: str) -> tuple[str, ...]:
    """The rules whose ``metric`` the parameter moves: those run again at each value (``BenchSweep.recomputed``),
    except that ``reference_share`` cuts the natural open set only, so it moves no rule's closed-set F1."""
    if metric == "closed" and sweep.parameter is Parameter.REFERENCE_SHARE:
        return ()
    return tuple(sweep.recomputed)


def value_label(parameter: Parameter | str, value: float) -> str:
    """A value's column head, e.g. ``"ds=4"`` (as ``acceptance_sweep.render`` heads its columns)."""
    return f"{parameter}={value:g}"


def sweep_figure(sweep: BenchSweep, metric: str, *, title: str = "") -> go.Figure:
    """One line per rule across the swept values for one metric (module doc).

    Traces: ``meta`` = the rule's key; ``x`` = the values in increasing order, ``y`` = the
    rule's ``sweep_value`` at each (NaN, a gap, where it did not run); ``customdata`` = τ at
    each value (NaN for a rule with thresholds of its own). A rule in ``sweep_affected`` is a
    solid line with markers, the others faint and dashed (``FAINT`` opacity).
    """
    order = np.argsort(np.asarray(sweep.values, dtype=float), kind="stable")
    points = [sweep.points[i] for i in order]
    x = [sweep.values[i] for i in order]
    affected = sweep_affected(sweep, metric)
    colours = rule_colours()
    what = SWEEP_METRICS[metric]
    p = sweep.parameter
    fig = go.Figure()
    for key in sweep_keys(sweep):
        rule = RULES_BY_KEY[key]
        moves = key in affected
        y = np.array([sweep_value(pt, key, metric) for pt in points], dtype=float)
        tau = np.array([pt.closed.tau.get(key, math.nan) for pt in points], dtype=float)
        fig.add_trace(go.Scatter(
            x=x, y=y, mode="lines+markers" if moves else "lines", meta=key, legendgroup=key,
            name=rule.label if moves else f"{rule.label} (does not read {p})",
            opacity=1.0 if moves else FAINT,
            line=dict(color=colours[key], width=2.5 if moves else 1.5, dash="solid" if moves else "dash"),
            marker=dict(size=7), customdata=tau,
            hovertemplate=(f"{p} = %{{x:g}}: {what} %{{y:.1f}}%"
                           + (" (τ %{customdata:.4g})" if rule.free else "") + f"<extra>{rule.label}</extra>"),
        ))
    fig.update_layout(title=title or f"{what} of every rule as {p} varies",
                      xaxis=dict(title=p.value, tickvals=x, ticktext=[f"{v:g}" for v in x]),
                      yaxis=dict(title=f"{what}, %", range=[-2, 102]),
                      height=460, margin=MARGIN, legend=dict(orientation="h", y=-0.2))
    return fig


def sweep_table(sweep: BenchSweep, metric: str) -> list[dict]:
    """One metric of a sweep as rows: ``key``, ``rule`` (label, "†" where τ is the oracle's at some value),
    ``reads`` (the parameter moves it: ``sweep_affected``), then one column per value (``value_label``, in
    the order given), percent."""
    affected = sweep_affected(sweep, metric)

    def label(key: str) -> str:
        oracle = any(pt.closed.tau_note.get(key, "").startswith("oracle") for pt in sweep.points)
        return RULES_BY_KEY[key].label + (" †" if oracle else "")

    return [{"key": key, "rule": label(key), "reads": key in affected,
             **{value_label(sweep.parameter, v): sweep_value(pt, key, metric)
                for v, pt in zip(sweep.values, sweep.points)}}
            for key in sweep_keys(sweep)]


def sweep_rows(sweep: BenchSweep) -> list[dict]:
    """Every number of a sweep, one dict per rule and value (rules in ``RULES`` order, values as given).

    Keys: ``key``, ``rule``, the parameter's name (its value), ``recomputed`` (run again at each
    value), ``closed F1``, ``R`` and ``P`` (closed set), ``AUC-PR`` (closed set), ``τ``,
    ``τ from``, ``open F1``, ``rejection`` (natural open set; NaN where it did not run or has no
    distractor), ``left out`` (why the rule did not run at this value, else empty).
    """
    p = sweep.parameter.value
    rows = []
    for key in sweep_keys(sweep):
        for v, pt in zip(sweep.values, sweep.points):
            c = pt.closed.counts.get(key)
            rows.append({
                "key": key, "rule": RULES_BY_KEY[key].label, p: v, "recomputed": key in sweep.recomputed,
                "closed F1": sweep_value(pt, key, "closed"),
                "R": math.nan if c is None else float(c.recall),
                "P": math.nan if c is None else float(c.precision),
                "AUC-PR": pt.closed.auc.get(key, math.nan),
                "τ": pt.closed.tau.get(key, math.nan),
                "τ from": pt.closed.tau_note.get(key, ""),
                "open F1": sweep_value(pt, key, "open"),
                "rejection": sweep_value(pt, key, "rejection"),
                "left out": pt.closed.left_out.get(key, ""),
            })
    return rows


# --------------------------------------------------------------------------- discovered places


def place_starts(place: np.ndarray) -> np.ndarray:
    """Frames where a place starts: a frame in a place whose previous frame is in another place or none."""
    place = np.asarray(place)
    prev = np.r_[-1, place[:-1]]
    return np.flatnonzero((place >= 0) & (place != prev))


def discovery_figure(group_step: np.ndarray, discovery: Discovery, *, group_label: str = "group/step",
                     title: str = "") -> go.Figure:
    """Group/step places and discovered places along the route, and the online score against θ under them.

    Args:
        group_step: ``(n_database,)`` place of each database image in route order, ``-1`` between places.
        discovery: ``place_discovery.discover`` on the same images in the same order.
        group_label: the name of the first band row.

    Traces: per band ``"places <band>"`` (place frames, ``customdata`` = place),
    ``"outside <band>"`` (frames in no place) and ``"starts <band>"`` (x = the frame a place
    starts at, drawn half a frame before it); below, ``"score"``, ``"θ"``, ``"below θ"``
    (frames at or under θ) and ``"online from"``.
    """
    group_step = np.asarray(group_step)
    found = np.asarray(discovery.place)
    n = len(found)
    frames = np.arange(n)
    bands = (group_label, "discovered")
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, row_heights=[0.35, 0.65], vertical_spacing=0.08,
                        subplot_titles=("places along the route", "online score of each frame against θ"))
    for band, place in zip(bands, (group_step, found)):
        inside = place >= 0
        fig.add_trace(go.Scatter(
            x=frames[~inside], y=[band] * int((~inside).sum()), mode="markers", name="frames in no place",
            legendgroup="outside", showlegend=band == bands[0], meta=f"outside {band}",
            marker=dict(symbol="line-ns-open", size=14, color=SKIPPED, line=dict(width=2, color=SKIPPED)),
            hovertemplate=f"frame %{{x}}: in no {band} place<extra></extra>",
        ), row=1, col=1)
        fig.add_trace(go.Scatter(
            x=frames[inside], y=[band] * int(inside.sum()), mode="markers", name=f"{band} places",
            showlegend=False, customdata=place[inside], meta=f"places {band}",
            marker=dict(symbol="square", size=8, color=place_colours(place[inside])),
            hovertemplate=f"frame %{{x}}: {band} place %{{customdata}}<extra></extra>",
        ), row=1, col=1)
        starts = place_starts(place)
        fig.add_trace(go.Scatter(
            x=starts - 0.5, y=[band] * len(starts), mode="markers", name="a place starts",
            legendgroup="starts", showlegend=band == bands[0], customdata=place[starts], meta=f"starts {band}",
            marker=dict(symbol="line-ns-open", size=22, color=INK, line=dict(width=2, color=INK)),
            hovertemplate=f"{band} place %{{customdata}} starts at frame %{{x:.0f}}<extra></extra>",
        ), row=1, col=1)
    fig.add_trace(go.Scatter(x=frames, y=discovery.score, mode="lines", name="score (mean similarity to the place)",
                             meta="score", line=dict(color=INK, width=1.5),
                             hovertemplate="frame %{x}: score %{y:.4f}<extra></extra>"), row=2, col=1)
    fig.add_trace(go.Scatter(x=frames, y=discovery.theta, mode="lines", name="θ = μ⁻ + n·σ⁻", meta="θ",
                             line=dict(color=THETA, width=1.5, dash="dot", shape="hv"),
                             hovertemplate="frame %{x}: θ %{y:.4f}<extra></extra>"), row=2, col=1)
    with np.errstate(invalid="ignore"):
        below = np.flatnonzero(discovery.score <= discovery.theta)
    fig.add_trace(go.Scatter(x=below, y=np.asarray(discovery.score)[below], mode="markers", meta="below θ",
                             name="at or below θ (pending)", marker=dict(size=5, color=THETA),
                             hovertemplate="frame %{x}: score %{y:.4f} ≤ θ<extra></extra>"), row=2, col=1)
    online = discovery.online_from
    if online < n:
        finite = np.r_[discovery.score[np.isfinite(discovery.score)], discovery.theta[np.isfinite(discovery.theta)]]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        fig.add_trace(go.Scatter(x=[online - 0.5, online - 0.5], y=[lo, hi], mode="lines", meta="online from",
                                 name=f"online from frame {online} (bootstrap before)",
                                 line=dict(color=BASELINE, width=1, dash="dash"), hoverinfo="skip"), row=2, col=1)
    fig.update_yaxes(type="category", categoryorder="array", categoryarray=list(bands[::-1]), row=1, col=1)
    fig.update_yaxes(title_text="similarity", row=2, col=1)
    fig.update_xaxes(title_text="database frame (route order)", row=2, col=1)
    fig.update_layout(title=title or None, height=520, margin={**MARGIN, "t": 60}, legend=dict(orientation="h", y=-0.15))
    return fig
