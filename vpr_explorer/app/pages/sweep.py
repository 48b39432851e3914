"""Group/step sweep page: one protocol over a grid of group × step, as heatmaps; a click sets group/step everywhere.

One body for every layout whose places group/step make. Aligned traversals sweep frames
under the paper, traversal and open-set protocols (on the traversals as loaded,
``cur.source``); any other dataset value sweeps the database/queries protocol (on
``cur.data``), group/step counting its database images in listed order, or metres along
its route or over a lattice when that is the geometry in use (set on the Places page).
Places the layout names (prepared places, a manifest's place column) leave nothing to sweep.

Widgets → one library call (``sweep.sweep``, with progress bars, its cells memoised in one
``SweepCache`` per server) → render (``sweep.sweep_figure``, one colour scale for both readings:
``sweep.colour_range``). The sweep's own settings (groups, steps, readings,
protocol, runs, method, metric) live in the URL as ``sweep_*`` page parameters; group/step
and the reading chosen by a click go into the view (``state.commit``), so every page uses them.

The traversal protocol's cells query the view's query traversal against every other one (the
database and queries of the **Places** page), so a cell of it reads what the Places page
reads for that group/step; the paper and open-set protocols draw their queries from every
traversal, and the page says so beside the grid, naming where the Places page's numbers come from.
"""

import pandas as pd  # before plotly: plotly.py#2433
import streamlit as st

from vpr_explorer import pipeline
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import GEOMETRY_LABELS, READING_LABELS, PlaceGeometry, Reading
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols.evaluation import PROTOCOL_LABELS, Protocol
from vpr_explorer.protocols.sweep import (
    ALIGNED_PROTOCOLS,
    BASELINE,
    METRIC_HELP,
    METRIC_LABELS,
    SPREAD_COLUMNS,
    SWEEP_METHODS,
    Metric,
    SweepCache,
    SweepSpec,
    check_data,
    colour_range,
    empty_reasons,
    missing_reasons,
    scale_note,
    selected_cell,
    sweep,
    sweep_cost,
    sweep_figure,
)

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import progress_reporter, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed, page_file

ensure_routed(__file__)

GRIDS = {"frames": {"sweep_groups": "1 2 3 5", "sweep_steps": "3 5 10 20"},
         "m": {"sweep_groups": "10 25 50", "sweep_steps": "50 100 200"}}
# the sweep's settings when the URL names none: a 4 × 4 grid of frames (3 × 3 of metres) in both readings,
# 5 splits a cell (the paper uses 50)
SETTINGS = {"sweep_readings": "stride skip", "sweep_runs": "5", "sweep_method": SWEEP_METHODS[0],
            "sweep_metric": Metric.R1.value}
MAX_SWEEP_RUNS = 50


@st.cache_resource(show_spinner=False)
def _cells() -> SweepCache:
    """Every evaluated cell of this server, by descriptors, options and places: sweeps share them."""
    return SweepCache()


def _numbers(text: str, name: str) -> tuple[int | float, ...]:
    """Numbers separated by spaces (or commas); whole ones as ``int``."""
    try:
        values = [float(x) for x in str(text).replace(",", " ").split()]
    except ValueError:
        raise VPRInputError(f"{name} {text!r}: give numbers separated by spaces, e.g. 1 2 3 5") from None
    return tuple(int(v) if v.is_integer() else v for v in values)


st.title("Group/step sweep")
with stop_on_input_error():
    cur = current()
geometry = cur.places.geometry
if geometry is None:
    st.info(f"Group/step do not apply: the layout names its places ({cur.dataset.layout.value}), so there is nothing "
            "to sweep. Its numbers are on the **Evaluation** page.", icon=":material/info:")
    st.stop()
aligned = cur.aligned is not None and geometry is PlaceGeometry.FRAMES
data = cur.source if aligned else cur.data  # aligned traversals' protocols read the traversals as loaded
protocols = ALIGNED_PROTOCOLS if aligned else (Protocol.DATABASE,)
unit = "frames" if geometry is PlaceGeometry.FRAMES else "m"
metres = "" if unit == "frames" else " m"  # after a number of metres; frames go unsaid
DEFAULTS = {**GRIDS[unit], **SETTINGS, "sweep_protocol": protocols[0].value}


def _spec(p: dict) -> SweepSpec:
    """The sweep the page parameters ``p`` describe; ``VPRInputError`` naming the one at fault."""
    try:
        runs = int(p["sweep_runs"])
    except ValueError:
        raise VPRInputError(f"runs {p['sweep_runs']!r}: give a whole number from 1 to {MAX_SWEEP_RUNS}") from None
    if not 1 <= runs <= MAX_SWEEP_RUNS:
        raise VPRInputError(f"runs={runs}: give a whole number from 1 to {MAX_SWEEP_RUNS}")
    # the traversal protocol queries the Places page's query traversal against the others (aligned traversals)
    traversals = dict(database=cur.database, queries=cur.query) if aligned else {}
    spec = SweepSpec(groups=_numbers(p["sweep_groups"], "groups"), steps=_numbers(p["sweep_steps"], "steps"),
                     readings=tuple(p["sweep_readings"].split()), protocol=p["sweep_protocol"], geometry=geometry,
                     method=p["sweep_method"], runs=runs, k=float(state.view().k), user_theta=state.view().theta,
                     **traversals)
    if spec.protocol not in protocols:
        if not aligned:
            check_data(data.dataset, spec)  # names why: the protocol needs aligned traversals
        raise VPRInputError(f"protocol {spec.protocol.value}: with these places the sweep runs "
                            f"{', '.join(p.value for p in protocols)}")
    return spec


def _canonical(p: dict, spec: SweepSpec) -> dict:
    """``p`` with the lists as the sweep reads them: sorted, each value once."""
    return {**p, "sweep_groups": " ".join(f"{g:g}" for g in spec.groups),
            "sweep_steps": " ".join(f"{s:g}" for s in spec.steps),
            "sweep_readings": " ".join(r.value for r in spec.readings)}


def _settings() -> tuple[dict, SweepSpec]:
    """The sweep's settings from the URL (page parameters), each refused one replaced by its default, said once."""
    given = {k: v for k, v in state.page_params().items() if k in DEFAULTS}
    p = {**DEFAULTS, **given}
    if p["sweep_metric"] not in {m.value for m in Metric}:
        st.warning(f"sweep_metric={p['sweep_metric']!r}: choose one of {', '.join(m.value for m in Metric)}; "
                   f"showing {DEFAULTS['sweep_metric']}", icon=":material/warning:")
        p["sweep_metric"] = DEFAULTS["sweep_metric"]
    try:
        spec = _spec(p)
        return _canonical(p, spec), spec
    except VPRInputError as exc:
        for name in given:  # the one refused setting back to its default, the others kept
            fixed = {**p, name: DEFAULTS[name]}
            try:
                spec = _spec(fixed)
            except VPRInputError:
                continue
            st.warning(f"{name}={p[name]!r} in the link was refused: {exc}. Using {DEFAULTS[name]!r} instead.",
                       icon=":material/warning:")
            return _canonical(fixed, spec), spec
        st.warning(f"The link's sweep settings were refused: {exc}. Using the defaults.", icon=":material/warning:")
        p = {**DEFAULTS, "sweep_metric": p["sweep_metric"]}
        spec = _spec(p)
        return _canonical(p, spec), spec


def _submit() -> None:
    """The form's values become the sweep's settings (in the URL), if they make a valid sweep."""
    ss = st.session_state
    p = {**state.page_params(), "sweep_groups": ss["w_sweep_groups"], "sweep_steps": ss["w_sweep_steps"],
         "sweep_readings": " ".join(ss["w_sweep_readings"]), "sweep_protocol": ss["w_sweep_protocol"],
         "sweep_runs": str(ss["w_sweep_runs"]), "sweep_method": ss["w_sweep_method"]}
    p = {**DEFAULTS, **{k: v for k, v in p.items() if k in DEFAULTS}}
    try:
        spec = _spec(p)
    except VPRInputError as exc:
        ss["rejected_sweep"] = str(exc)
        return
    state.set_page_params(**_canonical(p, spec))
    ss["sweep_go"] = True


def _pick(reading: str) -> None:
    """A click on a heatmap cell: that group/step (frames, or metres) and reading, for every page."""
    points = st.session_state[f"sweep_{reading}"].selection.points
    cell = selected_cell(points[0]) if points else None
    if cell is None:
        return
    group, step, reading = cell
    if unit == "frames":
        state.commit(group=group, step=step, reading=reading)
    else:
        state.commit(group_m=float(group), step_m=float(step), reading=reading)
    st.session_state["sweep_picked"] = cell


def protocol_note(spec: SweepSpec) -> str:
    """Which protocol a cell runs, and where the **Places** page's numbers for the same group/step come from."""
    if spec.protocol is Protocol.DATABASE:
        return (f"Each cell runs the {Protocol.DATABASE.value} protocol (one run): every query against the database, "
                "thresholds from the database only, as on the **Places** page: the same numbers for a group/step.")
    database = " + ".join(cur.database)
    if spec.protocol is Protocol.TRAVERSAL:
        return (f"Each cell runs the traversal protocol on the **Places** page's traversals: {cur.query} queried "
                f"against {database}, thresholds from the database only (one run). A cell's place-level R@1 is the "
                "one the Places page shows for that group/step.")
    draw = ("one image of every place is the query (from any traversal) and every other image, its own "
            "traversal's included, trains and is the database")
    if spec.protocol is Protocol.OPEN_SET:
        draw += f"; {spec.unknown_share:.0%} of the places are held out as unknown"
    return (f"Each cell runs the {spec.protocol.value} protocol: {spec.runs} random split{'s' if spec.runs != 1 else ''}"
            f" (seed {spec.seed}) in which {draw}; R@1 is the mean over the splits. The **Places** page shows another "
            f"protocol for the same group/step: the traversal protocol, the query traversal {cur.query} against the "
            f"database {database}, thresholds from the database only. Neighbouring frames of a query's own traversal "
            "make this protocol far easier, so its R@1 is higher. Choose the traversal protocol above for the Places "
            "page's numbers.")


how = (f"group/step in metres ({GEOMETRY_LABELS[geometry]}; the geometry is set on the **Places** page)"
       if unit == "m" else "group/step in frames" if cur.aligned is not None
       else "group/step counting database images in listed order")
protocols_run = ("the paper, traversal or open-set protocol of aligned traversals" if aligned
                 else f"the {Protocol.DATABASE.value} protocol")
st.markdown("Every cell of the grid is one run of the protocol with that group and step, on the descriptors already "
            "loaded (they are per image, so only the places change). Click a cell to use its group/step and reading "
            f"on every page. Here: {protocols_run}, {how}.")

params, spec = _settings()
ss = st.session_state
# the form starts from the settings in use (a widget's state is dropped when the page is left)
ss.setdefault("w_sweep_groups", params["sweep_groups"])
ss.setdefault("w_sweep_steps", params["sweep_steps"])
ss.setdefault("w_sweep_readings", [r.value for r in spec.readings])
if ss.get("w_sweep_protocol") not in [p.value for p in protocols]:
    ss["w_sweep_protocol"] = spec.protocol.value
ss.setdefault("w_sweep_runs", spec.runs)
ss.setdefault("w_sweep_method", spec.method)

with st.form("sweep_form"):
    c = st.columns([3, 3, 3])
    c[0].text_input(f"groups ({unit} per place)", key="w_sweep_groups", help="numbers separated by spaces")
    c[1].text_input(f"steps ({unit})", key="w_sweep_steps", help="numbers separated by spaces")
    c[2].multiselect("readings", [r.value for r in Reading], key="w_sweep_readings",
                     help=" · ".join(READING_LABELS[r] for r in Reading))
    c = st.columns([4, 2, 3])
    c[0].radio("protocol", [p.value for p in protocols], key="w_sweep_protocol",
               format_func=lambda p: PROTOCOL_LABELS[Protocol(p)])
    c[1].number_input("runs per cell (paper: 50)", 1, MAX_SWEEP_RUNS, key="w_sweep_runs", disabled=not aligned,
                      help="random splits of the paper and open-set protocols; the traversal and database/queries "
                           "protocols run once")
    c[2].selectbox("thresholded method (gain, rejection, AUC)", list(SWEEP_METHODS), key="w_sweep_method",
                   format_func=lambda k: METHODS_BY_KEY[k].label)
    st.form_submit_button("Run sweep", type="primary", on_click=_submit)

rejected = ss.pop("rejected_sweep", None)
if rejected:
    st.error(f"{rejected}\n\nThe previous sweep settings are kept.", icon=":material/error:")
state.set_page_params(**params)  # the settings in use, in the URL

ds = data.dataset
with stop_on_input_error(hint="Change the sweep's settings above."):
    cost = sweep_cost(ds, spec, cache=_cells(), descriptors_key=data.key)
go = ss.pop("sweep_go", False)
settings_line = (f"{PROTOCOL_LABELS[spec.protocol]}; {', '.join(r.value for r in spec.readings)} reading"
                 f"{'s' if len(spec.readings) > 1 else ''}"
                 + (f"; {spec.runs} runs per cell" if spec.protocol in (Protocol.PAPER, Protocol.OPEN_SET) else "")
                 + (f"; rejection at k = {spec.k:g} (the k of the **Thresholds** page)"
                    if spec.protocol is Protocol.OPEN_SET else "")
                 + ("; rejection of the queries with no right image, at θ_p (k = 0)"
                    if spec.protocol is Protocol.DATABASE else ""))
st.caption(f"**Cost:** {cost.describe()}. {settings_line}.")
st.info(protocol_note(spec), icon=":material/info:")
if cost.runs and cost.large and not go:
    st.warning(f"{ds.n_images:,} images: this sweep scores about **{cost.pairs:.1e} image pairs** in "
               f"{cost.runs} protocol runs (minutes to hours), so it does not start by itself. Trim the grid or the "
               "runs, or press **Run sweep**; a progress bar shows each cell, and finished cells are kept in memory.",
               icon=":material/timer:")
    st.stop()


def run_sweep():
    """The sweep, with a progress bar over its cells and one inside the running cell.

    Not through ``cache``'s memo of whole results: the cells are memoised one by one in
    ``_cells()`` (so an overlapping sweep reuses them), and a sweep of cells in memory
    takes milliseconds.
    """
    progress, clear = progress_reporter(f"Sweeping {cost.valid} cells ({cost.runs} protocol runs to do)")
    inner, clear_inner = progress_reporter("this cell")
    try:
        return sweep(ds, data.descriptors, spec, pipeline, descriptor=data.descriptor, descriptors_key=data.key,
                     cache=_cells(), shared=cache.shared_scores(data) if aligned else None, progress=progress,
                     cell_progress=inner)
    finally:
        clear_inner()
        clear()


with stop_on_input_error(hint="Change the sweep's settings above, or the dataset on the **Dataset** page."):
    result = run_sweep()

picked = ss.pop("sweep_picked", None)
if picked:
    st.success(f"group {picked[0]:g}{metres}, step {picked[1]:g}{metres} ({picked[2]} reading) is now in use on "
               "every page.",
               icon=":material/check_circle:")
    st.page_link(page_file("places"), label="See it on the Places page", icon=":material/place:")

metric = st.radio("metric", [m.value for m in Metric], format_func=lambda m: METRIC_LABELS[Metric(m)],
                  index=[m.value for m in Metric].index(params["sweep_metric"]), horizontal=True, key="w_sweep_metric",
                  on_change=lambda: state.set_page_params(sweep_metric=ss["w_sweep_metric"]))
method_label = METHODS_BY_KEY[spec.method].label
st.caption(METRIC_HELP[Metric(metric)] + (f" Method: {method_label}." if metric != Metric.R1 else "")
           + (" Hover a cell for its mean ± std over the splits and the 95% interval of the mean"
              + (" (the gain: the paired difference from the place level on the cell's splits, with its p-value)."
                 if metric == Metric.GAIN else ".") if spec.protocol in (Protocol.PAPER, Protocol.OPEN_SET) else ""))
v = cur.spec if unit == "frames" else cur.places.metric
zrange = colour_range(result, metric)
for col, reading in zip(st.columns(len(spec.readings)), spec.readings):
    with col:
        marked = (v.group, v.step) if v.reading is reading else None
        st.plotly_chart(sweep_figure(result, metric, reading, marked=marked, zrange=zrange),
                        key=f"sweep_{reading.value}", on_select=lambda r=reading.value: _pick(r),
                        selection_mode="points", width="stretch")
if zrange is not None:
    st.caption(scale_note(result, metric))
best = result.best(metric)
ran = sum(c.evaluation.seconds for c in result.cells if c.evaluation is not None and c.same_as is None)
st.caption(f"In use: group {v.group:g}{metres}, step {v.step:g}{metres} ({v.reading.value}), outlined. "
           + (f"Best {METRIC_LABELS[Metric(metric)]}: group {best.group:g}{metres}, step {best.step:g}{metres} "
              f"({best.reading.value}). " if best else "")
           + f"The protocol runs took {ran:.1f} s "
           "(each kept in memory); a cell shared by both readings (skip g/s = stride g/g+s) is run once.")
in_use = next((c for c in result.cells if (c.group, c.step, c.reading) == (v.group, v.step, v.reading)
               and not c.empty), None)
if in_use is not None:
    st.caption(f"In use, over the splits: {METHODS_BY_KEY[BASELINE].label} R@1 (%) {in_use.spread(Metric.R1)}; "
               f"{method_label} minus it (points) {in_use.spread(Metric.GAIN)}"
               + (f"; rejection (%) {in_use.spread(Metric.REJECTION)}" if in_use.spread(Metric.REJECTION) else "")
               + ".")
for line in empty_reasons(result):
    st.caption(f"empty: {line}")
for line in missing_reasons(result):
    st.caption(f"missing: {line}")

rows = pd.DataFrame([{**c.to_dict(), "missing": "; ".join(f"{k}: {w}" for k, w in c.missing.items()),
                      "same_as": "" if c.same_as is None else " ".join(map(str, c.same_as))} for c in result.cells])
rates = [c for c in SPREAD_COLUMNS if c.endswith(("_std", "_low", "_high"))]
for c in (Metric.R1.value, Metric.GAIN.value, Metric.REJECTION.value, *rates):
    rows[c] = rows[c].astype(float) * 100
with st.expander("Every cell as a table"):
    st.dataframe(rows, hide_index=True, key="sweep_table", column_config={
        **{m.value: st.column_config.NumberColumn(METRIC_LABELS[m], format="%.3f" if m is Metric.AUC else "%.1f")
           for m in Metric},
        **{c: st.column_config.NumberColumn(c.replace("_", " "), format="%.1f") for c in rates},
        "gain_p": st.column_config.NumberColumn("gain p (paired t-test)", format="%.4f")})
    st.caption("Rates in %, the gain in points: each metric's mean over the splits, its std (ddof 1) and the 95% "
               "Student-t interval of the mean (ci95 low/high); the gain's std, interval and p are those of the "
               "per-split differences from the place level (paired). The AUC is pooled over the splits.")
stem = (f"{ds.name}_{data.descriptor}_{spec.protocol.value}_sweep_g{'-'.join(f'{g:g}' for g in spec.groups)}"
        f"_s{'-'.join(f'{s:g}' for s in spec.steps)}{'' if unit == 'frames' else f'_{geometry.value}'}"
        f"_{'-'.join(r.value for r in spec.readings)}")
d1, d2 = st.columns(2)
d1.download_button("Download CSV", result.to_csv(), file_name=f"{stem}.csv", mime="text/csv", key="w_sweep_csv")
d2.download_button("Download JSON", result.to_json(), file_name=f"{stem}.json", mime="application/json",
                   key="w_sweep_json")
