"""Figures of runs compared (``compare``): one method's precision–recall curve and one trade-off curve per run.

A leaf like ``plots``: runs in, ``go.Figure`` out, no streamlit. Each run's trace has
``meta = "<kind> <run id>"`` (``"pr run 2"``, ``"own run 2"``, ``"tradeoff run 2"``) and is
named by the run's name, so a test reads a run's curve back by its id.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas  # noqa: F401  # imported before plotly: plotly.py#2433
import plotly.graph_objects as go

from vpr_explorer.protocols.compare import RunRecord
from vpr_explorer.views.plots import PALETTE
from vpr_explorer.method.retrieval import METHODS_BY_KEY

_MARGIN = dict(l=10, r=40, t=40, b=10)
#: Trade-off series a comparison can overlay (``Evaluation.tradeoff``'s series names).
TRADEOFF_SERIES = ("θ_p(k) weighted", "θ_p(k) simple", "global θ")


def _missing_note(fig: go.Figure, missing: Sequence[str], why: str) -> None:
    if missing:
        fig.add_annotation(text=f"not drawn ({why}): {', '.join(missing)}", xref="paper", yref="paper", x=0, y=1.0,
                           xanchor="left", yanchor="bottom", showarrow=False, font=dict(size=11))


def pr_overlay(runs: Sequence[RunRecord], method: str) -> go.Figure:
    """Precision (y) against recall (x) of one method in every run, with its own operating point.

    Each run's curve is the sweep its method sits on (``PRRow.curve``: the global θ, or
    θ_p(k) over k); its name gives the AUC and the queries with no true match (accepted,
    each is a false positive). Runs made without precision–recall, or without this
    method's curve, are named in a note above the plot.
    """
    fig = go.Figure()
    missing = []
    label = METHODS_BY_KEY[method].label if method in METHODS_BY_KEY else method
    for i, r in enumerate(runs):
        row = next((p for p in r.evaluation.pr if p.key == method), None)
        curve = r.evaluation.pr_curves.get(row.curve) if row is not None else None
        if curve is None:
            missing.append(r.name)
            continue
        colour = PALETTE[i % len(PALETTE)]
        auc = "—" if math.isnan(curve.auc) else f"{curve.auc:.3f}"
        fig.add_trace(go.Scatter(
            x=curve.recall, y=curve.precision, mode="lines", meta=f"pr {r.id}", line=dict(color=colour, width=2),
            name=f"{r.name}: AUC {auc}, {curve.n_unknown:,} with no true match",
            customdata=[float(t) if np.isfinite(t) else None for t in curve.threshold],
            hovertemplate=f"{curve.param}=%{{customdata:.3f}}: recall %{{x:.1%}}, precision %{{y:.1%}}"
                          f"<extra>{r.name}</extra>",
        ))
        own = row.own
        fig.add_trace(go.Scatter(
            x=[own.recall], y=[own.precision], mode="markers", meta=f"own {r.id}", showlegend=False,
            marker=dict(size=11, symbol="circle-open", color=colour, line=dict(width=3)),
            hovertemplate=f"{r.name}, own θ: recall %{{x:.1%}}, precision %{{y:.1%}}<extra></extra>",
        ))
    _missing_note(fig, missing, f"no precision–recall of {label}")
    fig.update_layout(title=f"Precision–recall of {label}, run by run (circles: the method's own θ)",
                      xaxis=dict(title="recall (of queries with a true match)", tickformat=".0%", range=[-0.02, 1.02]),
                      yaxis=dict(title="precision of accepted top-1", tickformat=".0%", range=[-0.02, 1.04]),
                      height=480, margin=_MARGIN, modebar=dict(orientation="v"), legend=dict(orientation="h", y=-0.25))
    return fig


def tradeoff_overlay(runs: Sequence[RunRecord], series: str = "θ_p(k) weighted", rule: str = "margin") -> go.Figure:
    """Open-set trade-off of every open-set run: unknown-place rejection (x) against known-place Recall@1 (y).

    ``series`` is a θ_p(k) family (its ``rule``: margin or raw) or ``"global θ"`` (the raw
    rule, whatever ``rule``); k = 0 is circled. Runs of a closed-set protocol have no
    unknown places and are named in a note.
    """
    if series not in TRADEOFF_SERIES:
        raise ValueError(f"series {series!r}: choose one of {', '.join(TRADEOFF_SERIES)}")
    fig = go.Figure()
    missing = []
    for i, r in enumerate(runs):
        pts = [t for t in r.evaluation.tradeoff if t.series == series and (series == "global θ" or t.rule == rule)]
        if not pts:
            missing.append(r.name)
            continue
        colour = PALETTE[i % len(PALETTE)]
        param = "θ" if series == "global θ" else "k"
        fig.add_trace(go.Scatter(
            x=[t.unknown_rejection[0] for t in pts], y=[t.known_recall1[0] for t in pts], mode="lines+markers",
            meta=f"tradeoff {r.id}", name=r.name, line=dict(color=colour), customdata=[t.param for t in pts],
            hovertemplate=f"{param}=%{{customdata:.3f}}: rejected %{{x:.0%}}, R@1 %{{y:.0%}}<extra>{r.name}</extra>",
        ))
        zero = [t for t in pts if t.param == 0.0 and series != "global θ"]
        if zero:
            fig.add_trace(go.Scatter(x=[zero[0].unknown_rejection[0]], y=[zero[0].known_recall1[0]], mode="markers",
                                     meta=f"k0 {r.id}", showlegend=False,
                                     marker=dict(size=15, symbol="circle-open", color=colour, line=dict(width=3)),
                                     hovertemplate=f"{r.name}, k = 0 (paper)<extra></extra>"))
    _missing_note(fig, missing, "not an open-set run")
    what = series if series == "global θ" else f"{series} ({rule})"
    fig.update_layout(title=f"Open set, run by run: {what}",
                      xaxis=dict(title="unknown-place queries rejected", tickformat=".0%", range=[-0.03, 1.03]),
                      yaxis=dict(title="known-place Recall@1", tickformat=".0%", range=[-0.03, 1.03]),
                      height=460, margin=_MARGIN, modebar=dict(orientation="v"), legend=dict(orientation="h", y=-0.25))
    return fig
