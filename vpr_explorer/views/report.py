"""Evaluations as text tables (the paper's Table 1 layout) and CSV rows.

Beside them, :func:`every_query_line`: the database-queries protocol's image-level
Recall@1/5/10 counted as VPR-methods-evaluation counts it (a hit rate over every query,
``protocols.evaluation.recall_over_every_query``), where the table counts it over the queries
that have a positive.
"""

from __future__ import annotations

import csv
import io
import math

from vpr_explorer.protocols.evaluation import Evaluation, Protocol, recall_over_every_query


def _pct(stat, with_std: bool = True) -> str:
    if stat is None or math.isnan(stat[0]):
        return "—"
    mean, std = stat
    if not with_std:
        return f"{100 * mean:5.1f}"
    return f"{100 * mean:5.1f} ± " + (f"{100 * std:4.1f}" if math.isfinite(std) else "   —")


def _grid(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    line = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows)])


def method_table(ev: Evaluation) -> str:
    """One row per method: Recall@K (%), accepted, precision, and the open-set/own-traversal columns."""
    std = ev.settings.get("runs", 1) > 1
    header = ["method", *(f"R@{k}" for k in ev.ks), "accepted", "precision"]
    own = any(r.own_traversal is not None for r in ev.rows)
    unk = any(r.unknown_rejection is not None for r in ev.rows)
    if unk:
        header.append("unknown rejected")
    if own:
        header.append("top-1 own trav.")
    rows = []
    for r in ev.rows:
        cells = [r.label, *(_pct(r.recall[k], std) for k in ev.ks), _pct(r.accepted, False), _pct(r.precision, False)]
        if unk:
            cells.append(_pct(r.unknown_rejection, False))
        if own:
            cells.append(_pct(r.own_traversal, False))
        rows.append(cells)
    return _grid(header, rows)


def every_query_line(ev: Evaluation) -> str | None:
    """The line ``vpr-explorer evaluate`` prints under a database-queries table when some queries have no
    positive (:func:`recall_over_every_query`), else ``None``."""
    recall = recall_over_every_query(ev)
    unknown = int(ev.settings.get("queries_without_positive", 0))
    if not recall or not unknown:
        return None
    ks = "/".join(map(str, recall))
    rates = " / ".join(f"{100 * x:.1f}" for x in recall.values())
    return (f"R@{ks} over every query, as VPR-methods-evaluation counts them: {rates} % ({ev.settings['queries']:,} "
            f"queries, {unknown:,} of them without a positive)")


def tradeoff_table(ev: Evaluation, rule: str = "margin") -> str:
    """The open-set trade-off: known-place R@1, unknown rejection and precision per k and global θ."""
    header = ["threshold", "k or θ", "known R@1", "unknown rejected", "precision", "accepted"]
    rows = []
    for t in ev.tradeoff:
        if t.rule != rule and not t.series.startswith("global"):
            continue
        param = "per place" if math.isnan(t.param) else (f"{t.param:+.2f}" if "k" in t.series else f"{t.param:.3f}")
        rows.append([f"{t.series} ({t.rule})", param, _pct(t.known_recall1), _pct(t.unknown_rejection),
                     _pct(t.precision), _pct(t.accepted, False)])
    return _grid(header, rows)


def _rate(x: float) -> str:
    return "—" if x is None or math.isnan(x) else f"{100 * x:5.1f}"


def at_text(value: float, param: str) -> str:
    """A point of a precision–recall curve by its parameter: ``θ=0.443`` (a global θ, three decimals), ``k=+0.27``
    (the per-place family's k), ``none`` for a method that accepts every query (−inf), ``—`` when undefined."""
    if math.isnan(value):
        return "—"
    if math.isinf(value) and value < 0:
        return "none"
    return f"k={value:+.2f}" if param == "k" else f"θ={value:.3f}"


def pr_table(ev: Evaluation) -> str:
    """Precision–recall per method, pooled over runs: the curve it sits on, AUC, R@100P, R@99P, max F1, its own point.

    AUC is the trapezoid ∫ P dR over the curve; rates in %; "at" is the θ or k of max F1 (``at_text``), "own at"
    the method's own θ or k (k = 0 for the per-place θ_p; the automatic θ of pooled runs: their mean); "own P"
    is "—" for a method that accepts no query.
    """
    header = ["method", "curve", "AUC", "R@100P", "R@99P", "max F1", "at", "own at", "own P", "own R", "known",
              "unknown"]
    rows = []
    for r in ev.pr:
        rows.append([r.label, r.curve, "—" if math.isnan(r.auc) else f"{r.auc:.3f}", _rate(r.r_at_100p),
                     _rate(r.r_at_99p), _rate(r.max_f1), at_text(r.max_f1_at, r.param),
                     at_text(r.own.threshold, r.param), _rate(r.own.precision if r.own.accepted else math.nan),
                     _rate(r.own.recall), f"{r.n_known:,}", f"{r.n_unknown:,}"])
    return _grid(header, rows)


#: Settings the header line leaves out: the k grid is the trade-off table's rows, group/step/reading are in
#: "places", and the traversal protocol's direction has a line of its own.
_NOT_IN_HEADER = frozenset({"k_grid", "group", "step", "reading", "direction"})


def render(ev: Evaluation) -> str:
    """The full text report of an evaluation."""
    s = ev.settings
    what = ", ".join(f"{k}={v}" for k, v in s.items() if k not in _NOT_IN_HEADER and v is not None)
    parts = [f"protocol: {ev.protocol.value}  ({what})"]
    if ev.protocol is Protocol.TRAVERSAL and "database" in s:
        database = ", ".join(map(str, s["database"]))
        parts.append(f"queries {s['queries']} against database {database}"
                     + (f" ({s['direction']})" if s.get("direction") else "") + f"; {s.get('places', '')}")
    parts += ["", method_table(ev)]
    if ev.protocol is Protocol.OPEN_SET:
        parts += ["", "trade-off over θ_p(k) = θ_p + k·s_p (k = 0 is the paper) and global θ:", "", tradeoff_table(ev)]
    if ev.pr:
        runs = ev.settings.get("runs", 1)
        pooled = f", pooled over {runs} runs" if runs > 1 else ""
        parts += ["", f"precision–recall (an accepted unknown-place query is a false positive; recall over known "
                      f"queries{pooled}):", "", pr_table(ev)]
    parts += ["", *(f"note: {n}" for n in ev.notes), f"({ev.seconds:.1f} s)"]
    return "\n".join(parts)


def method_csv(ev: Evaluation) -> str:
    """Method rows as CSV (rates in [0, 1])."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["protocol", "method", "label", *(f"R@{k} {x}" for k in ev.ks for x in ("mean", "std")),
                "accepted", "precision", "unknown_rejection", "own_traversal_top1"])
    for r in ev.rows:
        w.writerow([ev.protocol.value, r.key, r.label, *(v for k in ev.ks for v in r.recall[k]), r.accepted[0],
                    r.precision[0], r.unknown_rejection[0] if r.unknown_rejection else "",
                    r.own_traversal[0] if r.own_traversal else ""])
    for t in ev.tradeoff:
        w.writerow([ev.protocol.value, f"tradeoff:{t.series}:{t.rule}:{t.param}", t.series, t.known_recall1[0],
                    t.known_recall1[1], "", "", "", "", "", "", t.accepted[0], t.precision[0], t.unknown_rejection[0], ""])
    return buf.getvalue()
