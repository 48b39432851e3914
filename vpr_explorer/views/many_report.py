"""A bench (``protocols.many``) as one self-contained HTML page: its table, settings and figures.

The page loads nothing: the styles are inline, Plotly's JavaScript is inlined once in the
head (``plotly.offline.get_plotlyjs``, the library ``to_html(include_plotlyjs=True)`` embeds)
and each figure is its JSON in an inline script (``plotly.io.to_html``, ``full_html=False``,
Plotly's logo link hidden). What it shows:

* the bench's settings, the cells that ran and failed, and the seconds;
* the table (``BenchResult.rows``): one row per cell × method, rates in %, a failed cell's
  message across its row;
* the descriptors steps: source, images, seconds and both memory figures
  (``protocols.many.MEMORY_NOTES``);
* per dataset, a section (``id="dataset-N"``, ``data-dataset`` = its name) with its summary
  figure (``summary_figure``: Recall@1 ± std and the precision–recall AUC of every method,
  one bar per descriptor × protocol), then per cell that ran: the ``evaluate`` command that
  gives its numbers alone, its precision–recall figure (``plots.evaluation_pr_figure``), the
  open set's trade-off (``plots.tradeoff_figure``), and ``evaluate``'s text report of it.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence

import plotly.graph_objects as go
import plotly.io as pio
from plotly.subplots import make_subplots

from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.protocols.many import COLUMNS, MEMORY_NOTES, MIB, TABLE_KS, BenchCell, BenchResult
from vpr_explorer.views.plots import PALETTE, evaluation_pr_figure, tradeoff_figure
from vpr_explorer.views.report import render

#: Plotly's options for every figure: no logo link, resized with the page
CONFIG = {"displaylogo": False, "responsive": True}

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; max-width: 1400px; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; }
th { background: #f3f3f3; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.failed td { background: #fdecea; }
tr.missing td { color: #888; }
code, pre { background: #f7f7f7; }
pre { padding: 0.8em; overflow-x: auto; font-size: 0.8em; }
section.dataset { border-top: 2px solid #ddd; margin-top: 2em; }
details { margin: 1em 0; }
summary { cursor: pointer; font-weight: 600; }
.note { color: #555; font-size: 0.9em; }
"""


def _e(x) -> str:
    return html.escape("" if x is None else str(x))


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def _num(x, fmt: str) -> str:
    return "—" if x is None else fmt.format(x)


def _series(cell: BenchCell) -> str:
    return f"{cell.descriptor} · {cell.protocol.value}"


def summary_figure(result: BenchResult, source: str) -> go.Figure | None:
    """One dataset's methods side by side: Recall@1 (mean ± std over runs) above, AUC below.

    One bar series per descriptor × protocol that ran on it (``meta`` = ``"DESCRIPTOR ·
    PROTOCOL"``), methods along x in the table's order; ``None`` when no cell of the dataset ran.
    """
    rows = [r for r in result.rows() if r["source"] == source and r["status"] == "ok"]
    cells = [c for c in result.cells if c.source == source and c.evaluation is not None]
    if not cells:
        return None
    name = cells[0].dataset
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.08,
                        subplot_titles=("Recall@1 (mean ± std over runs)", "precision–recall AUC (pooled over runs)"))
    for i, cell in enumerate(cells):
        mine = [r for r in rows if r["descriptor"] == cell.descriptor and r["protocol"] == cell.protocol.value]
        labels = [r["label"] for r in mine]
        colour = PALETTE[i % len(PALETTE)]
        nan = lambda x: math.nan if x is None else x  # noqa: E731
        fig.add_trace(go.Bar(x=labels, y=[nan(r["r1"]) for r in mine], name=_series(cell), meta=_series(cell),
                             legendgroup=_series(cell), marker_color=colour,
                             error_y=dict(type="data", array=[r["r1_std"] or 0.0 for r in mine])), row=1, col=1)
        fig.add_trace(go.Bar(x=labels, y=[nan(r["auc"]) for r in mine], name=_series(cell),
                             meta=f"AUC {_series(cell)}", legendgroup=_series(cell), marker_color=colour,
                             showlegend=False), row=2, col=1)
    fig.update_layout(barmode="group", title=f"{name}: every method, descriptor and protocol", height=620,
                      legend=dict(orientation="h", y=-0.12), margin=dict(l=60, r=20, t=80, b=40))
    fig.update_yaxes(range=[0, 1.05], tickformat=".0%", row=1, col=1)
    fig.update_yaxes(range=[0, 1.05], row=2, col=1)
    return fig


class _Figures:
    """Numbers each figure's ``div`` of one page (``bench-fig-N``, or a given id)."""

    def __init__(self) -> None:
        self.count = 0

    def html(self, fig: go.Figure, div_id: str | None = None) -> str:
        self.count += 1
        return pio.to_html(fig, include_plotlyjs=False, full_html=False, config=CONFIG,
                           div_id=div_id or f"bench-fig-{self.count}")


def _settings_table(result: BenchResult) -> str:
    rows = []
    for k, v in result.spec.to_dict().items():
        shown = ", ".join(map(str, v)) if isinstance(v, list) else ("—" if v is None else v)
        if k == "descriptor_files":
            shown = ", ".join(f"{f['dataset']}={f['file']}" for f in v) or "—"
        rows.append(f"<tr><th>{_e(k)}</th><td>{_e(shown)}</td></tr>")
    return "<table class=\"settings\">" + "".join(rows) + "</table>"


def _results_table(result: BenchResult) -> str:
    head = ["dataset", "descriptor", "protocol", "method", *(f"R@{k}" for k in TABLE_KS), "AUC", "R@100P", "max F1",
            "rejected", "accepted", "precision", "extract s", "peak MiB", "RSS+ MiB"]
    out = ["<table class=\"results\"><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for r in result.rows():
        first = [r["dataset"], r["descriptor"], r["protocol"] or "—"]
        cost = [_num(r["extract_seconds"], "{:.1f}"), _num(r["python_peak_mib"], "{:.1f}"),
                _num(r["rss_growth_mib"], "{:.1f}")]
        cells = "".join(f"<td>{_e(x)}</td>" for x in first)
        if r["status"] == "failed":
            out.append(f"<tr class=\"failed\">{cells}<td colspan=\"{len(head) - 6}\">failed: {_e(r['message'])}</td>"
                       + "".join(f"<td class=\"num\">{x}</td>" for x in cost) + "</tr>")
            continue
        recall = [f"{_pct(r[f'r{k}'])}" + ("" if r[f"r{k}_std"] is None else f" ± {100 * r[f'r{k}_std']:.1f}")
                  if r[f"r{k}"] is not None else "—" for k in TABLE_KS]
        numbers = [*recall, _num(r["auc"], "{:.3f}"), _pct(r["r_at_100p"]), _pct(r["max_f1"]), _pct(r["rejection"]),
                   _pct(r["accepted"]), _pct(r["precision"]), *cost]
        label = r["label"] + (f" (missing: {r['message']})" if r["status"] == "missing" else "")
        out.append(f"<tr class=\"{r['status']}\">{cells}<td title=\"{_e(r['method'])}\">{_e(label)}</td>"
                   + "".join(f"<td class=\"num\">{_e(x)}</td>" for x in numbers) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _descriptors_table(result: BenchResult) -> str:
    head = ["dataset", "descriptor", "from", "images", "dim", "dtype", "cached before", "seconds", "peak MiB (Python)",
            "RSS growth MiB", "error"]
    names = {d.source: d.name for d in result.datasets}
    out = ["<table class=\"descriptors\"><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for d in result.descriptors:
        if d.source:
            origin = d.source.get("descriptors_file", "file")
        else:
            origin = "not run" if d.seconds is None and d.error is None else "extractor, through the cache"
        mib = lambda b: "—" if b is None else f"{b / MIB:.1f}"  # noqa: E731
        cells = [names.get(d.dataset, d.dataset), d.descriptor, origin, d.n_images, d.dim, d.dtype, d.cached_images,
                 _num(d.seconds, "{:.2f}"), mib(d.python_peak), mib(d.rss_growth), d.error or ""]
        out.append("<tr>" + "".join(f"<td>{_e('—' if x is None else x)}</td>" for x in cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _cell_html(cell: BenchCell, command: str | None, figures: _Figures) -> str:
    title = f"{cell.descriptor} · {cell.protocol.value if cell.protocol else '—'}"
    if cell.evaluation is None:
        return f"<p class=\"note\">{_e(title)}: failed: {_e(cell.error)}</p>"
    ev = cell.evaluation
    parts = [f"<details open><summary>{_e(title)} ({cell.seconds:.1f} s)</summary>"]
    if command:
        parts.append(f"<p class=\"note\">the same numbers alone: <code>{_e(command)}</code></p>")
    if ev.pr_curves:
        fig = evaluation_pr_figure(ev)
        fig.update_layout(title=f"{cell.dataset} · {title}: precision–recall, pooled over runs")
        parts.append(figures.html(fig))
    if ev.protocol is Protocol.OPEN_SET and ev.tradeoff:
        parts.append(figures.html(tradeoff_figure(ev)))
    parts.append(f"<pre>{_e(render(ev))}</pre></details>")
    return "".join(parts)


def bench_html(result: BenchResult, *, command: str | None = None, commands: Sequence[str] | None = None,
               title: str = "vpr-explorer bench") -> str:
    """The bench as one HTML document that loads nothing from elsewhere (module doc).

    Args:
        result: what ``protocols.many.run_bench`` returned.
        command: the command line that ran it, shown at the top.
        commands: per cell of ``result.cells``, the ``evaluate`` command that gives its numbers alone.

    Returns:
        The document, ``<!DOCTYPE html>`` first.
    """
    from plotly.offline import get_plotlyjs

    figures = _Figures()
    by_cell = dict(zip(map(id, result.cells), commands or ()))
    sections = []
    for k, d in enumerate(result.datasets, 1):
        parts = [f"<section class=\"dataset\" id=\"dataset-{k}\" data-dataset=\"{_e(d.name)}\">",
                 f"<h2>{_e(d.name)}</h2>", f"<p class=\"note\">{_e(d.source)}"
                 + (f" · {_e(d.layout)} · {d.n_images:,} images · {_e(d.description)}" if d.error is None else "")
                 + "</p>"]
        parts += [f"<p class=\"note\">{_e(n)}</p>" for n in d.notes]
        if d.error is not None:
            parts.append(f"<p class=\"note\">cannot be read: {_e(d.error)}</p>")
        fig = summary_figure(result, d.source)
        if fig is not None:
            parts.append(figures.html(fig, f"dataset-{k}-summary"))
        elif d.error is None:
            parts.append("<p class=\"note\">no cell of this dataset ran: see the table</p>")
        parts += [_cell_html(c, by_cell.get(id(c)), figures) for c in result.cells if c.source == d.source]
        parts.append("</section>")
        sections.append("".join(parts))
    script = f"<script type=\"text/javascript\">{get_plotlyjs()}</script>" if figures.count else ""
    failed = len(result.failed)
    head = (f"<p>{len(result.cells)} cells, {failed} failed · {result.seconds:.1f} s. Every cell is one "
            "<code>vpr-explorer evaluate --pr</code> run of the same settings.</p>")
    if command:
        head += f"<p><code>{_e(command)}</code></p>"
    notes = "".join(f"<li><b>{_e(k)}</b>: {_e(v)}</li>" for k, v in
                    (("peak MiB", MEMORY_NOTES[0]), ("RSS growth MiB", MEMORY_NOTES[1])))
    columns = "".join(f"<li><b>{_e(k)}</b>: {_e(v)}</li>" for k, v in COLUMNS.items())
    return "".join([
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">",
        f"<title>{_e(title)}</title><style>{STYLE}</style>", script, "</head><body>",
        f"<h1>{_e(title)}</h1>", head,
        "<h2>Results</h2>", _results_table(result),
        "<h2>Descriptors</h2>", _descriptors_table(result), f"<ul class=\"note\">{notes}</ul>",
        "<h2>Settings</h2>", _settings_table(result),
        *sections,
        f"<h2>Columns (bench.csv)</h2><ul class=\"note\">{columns}</ul>",
        "</body></html>",
    ])
