"""Runs side by side: evaluations kept as records, compared metric by metric, exported with their settings.

A **run** is one ``Evaluation`` and the settings that made it (dataset, descriptor,
group/step and reading, protocol, runs, seed, cross-condition, tolerance, traversals, θ …),
as ``pipeline.run_protocol`` records them in ``Evaluation.settings``. Runs on different
datasets, descriptors, places or tolerances are comparable: a comparison is a table of
numbers per method, whatever made them.

* ``RunRecord`` / ``record``: one run, with an id, a name the user may change, a pin;
* ``add_run``, ``rename``, ``pin``, ``remove``: a list of runs kept as a tuple (pure: each
  returns a new tuple); unpinned runs beyond ``MAX_RUNS`` are dropped oldest first;
* ``metric_table``: chosen metrics × methods across runs, with a difference column
  (run − reference) for every run but the reference;
* ``settings_rows``: every setting of every run, the settings that differ first;
* ``runs_csv`` / ``read_runs_csv``, ``runs_json`` / ``read_runs_json``: exports with every
  setting in columns (and ``export_stem``: in the file name), and their round trip.

Rates are in [0, 1] everywhere, as in ``Evaluation``; a difference is in the same unit
(0.05 = 5 points). A metric a run does not have (the precision–recall of a run made
without it, the unknown-place rejection of a closed-set protocol) is NaN, its difference
too, never 0. No streamlit here: ``vpr_explorer.app.ui.runs`` draws this.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation, strict
from vpr_explorer.method.retrieval import METHODS_BY_KEY

#: Unpinned runs kept; the oldest unpinned one goes when another arrives.
MAX_RUNS = 12

#: The settings that shape a run, in the order exports list them (others follow, sorted).
SETTING_COLUMNS = ("dataset", "descriptor", "protocol", "places", "group", "step", "reading", "runs", "seed",
                   "cross_condition", "unknown_share", "tolerance", "database", "queries", "theta")
#: Settings that describe a run's outcome rather than choose it: listed, never in the file name.
_DERIVED = {"places", "queries_per_run", "unknown_places_per_run", "known_places_per_run", "queries_scored",
            "queries_between_places", "direction", "k_grid"}
#: Short names of the settings in a file name (``g3``, ``tol2`` …); the rest appear as their values.
_STEM = {"group": "g", "step": "s", "runs": "r", "seed": "seed", "tolerance": "tol", "unknown_share": "unk",
         "database": "db-", "queries": "q-", "theta": "theta", "cross_condition": "cross-", "precision_recall": "pr-"}


def _recall_at(k: int) -> Callable[[Evaluation, str], float]:
    return lambda ev, key: _row_stat(ev, key, lambda r: r.recall.get(k, (math.nan,))[0])


def _row_stat(ev: Evaluation, key: str, get) -> float:
    row = next((r for r in ev.rows if r.key == key), None)
    if row is None:
        return math.nan
    value = get(row)
    return math.nan if value is None else float(value)


def _pr_stat(name: str) -> Callable[[Evaluation, str], float]:
    def value(ev: Evaluation, key: str) -> float:
        row = next((r for r in ev.pr if r.key == key), None)
        return math.nan if row is None else float(getattr(row, name))
    return value


#: metric name -> (what it is, value of one method in one run). Rates in [0, 1].
METRICS: dict[str, tuple[str, Callable[[Evaluation, str], float]]] = {
    **{f"R@{k}": (f"Recall@{k}, mean over runs: a known-place query is right when a right place is among the "
                  f"first {k} answers", _recall_at(k)) for k in (1, 3, 5, 10)},
    "accepted": ("share of queries given an answer (not rejected), mean over runs",
                 lambda ev, key: _row_stat(ev, key, lambda r: r.accepted[0])),
    "precision": ("share of accepted top-1 answers that are right, mean over runs",
                  lambda ev, key: _row_stat(ev, key, lambda r: r.precision[0])),
    "unknown rejected": ("share of unknown-place queries rejected (open set), mean over runs",
                         lambda ev, key: _row_stat(ev, key, lambda r: None if r.unknown_rejection is None
                                                   else r.unknown_rejection[0])),
    "own-traversal top-1": ("share of accepted top-1 answers from the query's own traversal, mean over runs",
                            lambda ev, key: _row_stat(ev, key, lambda r: None if r.own_traversal is None
                                                      else r.own_traversal[0])),
    "AUC": ("area under the precision–recall curve (trapezoids), pooled over runs", _pr_stat("auc")),
    "R@100P": ("recall at 100% precision, pooled over runs", _pr_stat("r_at_100p")),
    "R@99P": ("recall at 99% precision, pooled over runs", _pr_stat("r_at_99p")),
    "max F1": ("the best F1 = 2PR/(P + R) over the sweep, pooled over runs", _pr_stat("max_f1")),
}
DEFAULT_METRICS = ("R@1", "precision", "AUC", "R@100P", "max F1")


# --------------------------------------------------------------------------- one run


@dataclass(frozen=True, eq=False)
class RunRecord:
    """One run kept for comparison.

    Attributes:
        id: unique within a list (``"run 3"``), never reused.
        name: what the user calls it (unique within a list; ``rename``).
        settings: every setting of the run, flat (lists joined with ``+``), ``protocol`` included.
        evaluation: the protocol's result.
        pinned: kept however many runs follow.
    """

    id: str
    name: str
    settings: Mapping[str, object]
    evaluation: Evaluation
    pinned: bool = False

    def value(self, metric: str, key: str) -> float:
        """One metric of one method (NaN where this run does not have it)."""
        return METRICS[metric][1](self.evaluation, key)


def _flat(value: object) -> object:
    if isinstance(value, (list, tuple)):
        return "+".join(str(v) for v in value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def run_settings(ev: Evaluation, extra: Mapping[str, object] | None = None) -> dict[str, object]:
    """A run's settings, flat: ``protocol`` and ``ev.settings`` (lists as ``a+b``), then ``extra``; ``None`` left out."""
    raw = {"protocol": ev.protocol.value, **ev.settings, **(extra or {})}
    return {k: _flat(v) for k, v in raw.items() if _flat(v) is not None}


def settings_key(settings: Mapping[str, object]) -> tuple:
    """Settings as a hashable value: two runs with equal keys are the same run (the protocols are deterministic)."""
    return tuple(sorted((k, str(v)) for k, v in settings.items() if k not in _DERIVED))


def record(ev: Evaluation, *, run_id: str, name: str | None = None,
           extra: Mapping[str, object] | None = None) -> RunRecord:
    """A ``RunRecord`` of ``ev``; the name defaults to the id and the settings that tell runs apart."""
    settings = run_settings(ev, extra)
    if name is None:
        parts = [str(settings.get(k)) for k in ("protocol", "descriptor") if settings.get(k) is not None]
        name = f"{run_id}: {' · '.join(parts)}" if parts else run_id
    return RunRecord(run_id, name, settings, ev)


# --------------------------------------------------------------------------- the list


def _find(runs: Sequence[RunRecord], run_id: str) -> int:
    for i, r in enumerate(runs):
        if r.id == run_id:
            return i
    raise VPRInputError(f"no run {run_id!r} (runs: {', '.join(r.id for r in runs) or 'none'})")


def next_id(runs: Sequence[RunRecord], issued: int) -> str:
    """``"run N"`` with N one more than ``issued`` and than any id in ``runs`` (ids are never reused)."""
    numbers = [int(m.group(1)) for r in runs if (m := re.fullmatch(r"run (\d+)", r.id))]
    return f"run {max([issued, *numbers]) + 1}"


def add_run(runs: Sequence[RunRecord], new: RunRecord, *, max_runs: int = MAX_RUNS) -> tuple[RunRecord, ...]:
    """``runs`` with ``new`` at the end, unless a run of the same settings is there (then unchanged).

    Beyond ``max_runs`` unpinned runs, the oldest unpinned ones are dropped. A name already
    taken gets `` (2)``, `` (3)`` … appended.
    """
    key = settings_key(new.settings)
    if any(settings_key(r.settings) == key for r in runs):
        return tuple(runs)
    if any(r.id == new.id for r in runs):
        raise VPRInputError(f"run id {new.id!r} is taken: use next_id")
    name, n = new.name, 1
    while any(r.name == name for r in runs):
        n += 1
        name = f"{new.name} ({n})"
    out = [*runs, dataclasses.replace(new, name=name)]
    unpinned = [r for r in out if not r.pinned]
    drop = {r.id for r in unpinned[:max(0, len(unpinned) - max_runs)]}
    return tuple(r for r in out if r.id not in drop)


def find_run(runs: Sequence[RunRecord], settings: Mapping[str, object]) -> RunRecord | None:
    """The run of these settings, if kept."""
    key = settings_key(settings)
    return next((r for r in runs if settings_key(r.settings) == key), None)


def rename(runs: Sequence[RunRecord], run_id: str, name: str) -> tuple[RunRecord, ...]:
    """``runs`` with one run renamed; a blank name or one another run has is refused."""
    i = _find(runs, run_id)
    name = str(name).strip()
    if not name:
        raise VPRInputError(f"{run_id}: a run's name cannot be empty")
    if any(r.name == name and r.id != run_id for r in runs):
        raise VPRInputError(f"{run_id}: another run is already called {name!r}; choose another name")
    return (*runs[:i], dataclasses.replace(runs[i], name=name), *runs[i + 1:])


def pin(runs: Sequence[RunRecord], run_id: str, pinned: bool = True) -> tuple[RunRecord, ...]:
    """``runs`` with one run pinned (kept whatever follows) or unpinned."""
    i = _find(runs, run_id)
    return (*runs[:i], dataclasses.replace(runs[i], pinned=bool(pinned)), *runs[i + 1:])


def remove(runs: Sequence[RunRecord], run_id: str) -> tuple[RunRecord, ...]:
    """``runs`` without one run."""
    i = _find(runs, run_id)
    return (*runs[:i], *runs[i + 1:])


# --------------------------------------------------------------------------- comparing


def methods_of(runs: Iterable[RunRecord]) -> list[str]:
    """Method keys of the runs, in the order they first appear."""
    keys: list[str] = []
    for r in runs:
        for row in r.evaluation.rows:
            if row.key not in keys:
                keys.append(row.key)
    return keys


def difference_column(run: RunRecord, reference: RunRecord) -> str:
    """The header of ``run``'s difference column."""
    return f"Δ {run.name} − {reference.name}"


def metric_table(runs: Sequence[RunRecord], metrics: Sequence[str] = DEFAULT_METRICS, *,
                 methods: Sequence[str] | None = None, reference: str | None = None) -> list[dict[str, object]]:
    """Chosen metrics across runs: one row per method and metric, one column per run, and differences.

    Args:
        runs: the runs compared (columns, in this order, headed by their names).
        metrics: names of ``METRICS``.
        methods: method keys (rows); default every method of any run.
        reference: id of the run the others are compared with; default the first.
    Returns:
        rows ``{"method": label, "key": method key, "metric": name, <run name>: value, …,
        "Δ <run> − <reference>": run − reference, …}``; a value a run lacks is NaN, its
        difference too.
    """
    if not runs:
        raise VPRInputError("compare: choose at least one run")
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise VPRInputError(f"metric(s) {', '.join(map(repr, unknown))}: choose from {', '.join(METRICS)}")
    ref = runs[_find(runs, reference)] if reference is not None else runs[0]
    keys = list(methods) if methods is not None else methods_of(runs)
    bad = [k for k in keys if k not in METHODS_BY_KEY]
    if bad:
        raise VPRInputError(f"method(s) {', '.join(map(repr, bad))}: choose from {', '.join(METHODS_BY_KEY)}")
    rows = []
    for key in keys:
        for metric in metrics:
            row: dict[str, object] = {"method": METHODS_BY_KEY[key].label, "key": key, "metric": metric}
            base = ref.value(metric, key)
            for r in runs:
                row[r.name] = r.value(metric, key)
            for r in runs:
                if r.id != ref.id:
                    row[difference_column(r, ref)] = row[r.name] - base  # NaN stays NaN
            rows.append(row)
    return rows


def setting_names(runs: Sequence[RunRecord]) -> list[str]:
    """Every setting any run has: ``SETTING_COLUMNS`` first, then the rest sorted."""
    present = {k for r in runs for k in r.settings}
    return [k for k in SETTING_COLUMNS if k in present] + sorted(present - set(SETTING_COLUMNS))


def differing_settings(runs: Sequence[RunRecord]) -> list[str]:
    """The settings (not the derived counts) whose values are not the same in every run."""
    return [k for k in setting_names(runs) if k not in _DERIVED
            and len({str(r.settings.get(k)) for r in runs}) > 1]


def settings_rows(runs: Sequence[RunRecord]) -> list[dict[str, object]]:
    """One row per run: id, name, pinned, then every setting, the differing ones first (missing: ``None``)."""
    names = setting_names(runs)
    differ = differing_settings(runs)
    order = differ + [k for k in names if k not in differ]
    return [{"run": r.id, "name": r.name, "pinned": r.pinned, **{k: r.settings.get(k) for k in order}} for r in runs]


# --------------------------------------------------------------------------- exports


def _stem_part(name: str, value: object) -> str:
    if isinstance(value, bool) or name == "cross_condition":
        return "cross" if str(value) == "True" else "nocross"
    return f"{_STEM.get(name, '')}{value}"


def export_stem(runs: Sequence[RunRecord], prefix: str = "vpr_runs", max_length: int = 180) -> str:
    """A file name (no extension) carrying the settings: shared ones once, differing ones as ``a-vs-b``.

    E.g. ``vpr_runs_GardensPointWalking_pixels-vs-efficientnet-lite0_paper_g3_s10_stride_r20_seed0_nocross_tol0``.
    Characters other than letters, digits and ``._+-`` become ``-``; cut at ``max_length``.
    """
    parts = [prefix]
    for name in setting_names(runs):
        if name in _DERIVED:
            continue
        values = []
        for r in runs:
            v = r.settings.get(name)
            text = "none" if v is None else _stem_part(name, v)
            if text not in values:
                values.append(text)
        if values != ["none"]:
            parts.append("-vs-".join(values))
    stem = re.sub(r"[^A-Za-z0-9._+-]", "-", "_".join(parts))
    return stem[:max_length].rstrip("_-")


def _csv_value(x: object) -> object:
    if isinstance(x, float) and not math.isfinite(x):
        return ""
    return x


def runs_csv(runs: Sequence[RunRecord], metrics: Sequence[str] = tuple(METRICS)) -> str:
    """One row per run and method: run id, name, pinned, every setting (columns), method key and label, each metric.

    Rates in [0, 1]; a metric a run lacks is an empty cell.
    """
    names = setting_names(runs)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["run", "name", "pinned", *names, "method", "label", *metrics])
    for r in runs:
        for row in r.evaluation.rows:
            w.writerow([r.id, r.name, r.pinned, *(_csv_value(r.settings.get(k, "")) for k in names), row.key, row.label,
                        *(_csv_value(r.value(m, row.key)) for m in metrics)])
    return buf.getvalue()


def read_runs_csv(text: str) -> list[dict[str, object]]:
    """``runs_csv`` back: one dict per row, metrics as floats (NaN for empty), other columns as text."""
    rows = list(csv.DictReader(io.StringIO(text)))
    out = []
    for row in rows:
        parsed: dict[str, object] = dict(row)
        for m in METRICS:
            if m in row:
                parsed[m] = float(row[m]) if row[m] != "" else math.nan
        out.append(parsed)
    return out



def runs_json(runs: Sequence[RunRecord], metrics: Sequence[str] = DEFAULT_METRICS, *,
              reference: str | None = None) -> str:
    """Strict JSON (NaN as ``null``): every run with its settings and its whole ``Evaluation.to_dict()``, and the
    comparison table of ``metrics`` against ``reference``."""
    ref = runs[_find(runs, reference)] if reference is not None and runs else (runs[0] if runs else None)
    data = {
        "setting_names": setting_names(runs),
        "differing_settings": differing_settings(runs),
        "runs": [{"id": r.id, "name": r.name, "pinned": r.pinned, "settings": dict(r.settings),
                  "evaluation": r.evaluation.to_dict()} for r in runs],
        "comparison": {"reference": None if ref is None else ref.id, "metrics": list(metrics),
                       "rows": metric_table(runs, metrics, reference=None if ref is None else ref.id) if runs else []},
    }
    return json.dumps(strict(data), indent=1)


def read_runs_json(text: str) -> dict:
    """``runs_json`` back (``null`` for a missing number), refusing anything else with a clear error."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise VPRInputError(f"not a runs export (invalid JSON: {exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("runs"), list):
        raise VPRInputError("not a runs export: expected an object with a 'runs' list (vpr_explorer.protocols.compare.runs_json)")
    return data
