"""Runs side by side: evaluations kept as records, compared metric by metric, exported with their settings.

A **run** is one ``Evaluation`` and the settings that made it (dataset, descriptor,
group/step and reading, protocol, runs, seed, cross-condition, tolerance, traversals, θ …),
as ``pipeline.run_protocol`` records them in ``Evaluation.settings``. Runs on different
datasets, descriptors, places or tolerances are comparable: a comparison is a table of
numbers per method, whatever made them.

* ``RunRecord`` / ``record``: one run, with an id, a name the user may change, a pin;
* ``add_run``, ``rename``, ``pin``, ``remove``: a list of runs kept as a tuple (pure: each
  returns a new tuple); unpinned runs beyond ``MAX_RUNS`` are dropped oldest first;
* ``metric_table``: chosen metrics × methods across runs (means), with a difference column
  (run − reference) for every run but the reference; ``metric_stats``: the same cells as
  ``paired.Summary`` (mean ± std, 95% interval) and ``paired.Difference`` values;
* ``same_splits``: whether two runs scored the same splits, read from their settings;
  ``difference`` (one metric of one method, run − reference) and ``method_difference``
  (two methods of one run) compare split by split where the splits are the same;
* ``settings_rows``: every setting of every run, the settings that differ first;
* ``runs_csv`` / ``read_runs_csv``, ``runs_json`` / ``read_runs_json``: exports with every
  setting in columns (and ``export_stem``: in the file name), each metric's mean with its
  std, count and 95% interval, and their round trip.

**Over splits** (``paired`` states the formulas): a rate the protocol counts split by
split (Recall@K, accepted, precision, unknown rejected, own-traversal top-1;
``MethodRow.per_split``) is shown as mean ± std (ddof 1) over the splits with the 95%
Student-t interval of the mean. The precision–recall numbers (AUC, R@100P, R@99P, max F1)
are pooled over the splits (one curve of every split's queries): one number, no interval.

**Same splits.** ``evaluation.draw_splits`` draws a run's splits from its places, its number
of runs and its seed alone (the open set also from its share of unknown places). Two runs
of the same protocol whose recorded ``dataset``, ``places``, ``group``, ``step``,
``reading``, ``runs`` and ``seed`` (and ``unknown_share``) agree therefore scored the same
query images in the same splits, whatever their descriptors, tolerance, θ or
cross-condition: their difference is **paired** (per-split differences, their interval, the
paired t-test). Two runs that differ in any of those are compared by Welch's test and
marked **splits differ**, naming the setting. The traversal and database/queries protocols
run once (one "split"): the same dataset, places, database and queries are the same
queries, with no interval and no test. Two methods of one run always share its splits.

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
from pathlib import Path

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols import paired
from vpr_explorer.protocols.evaluation import Evaluation, Protocol, strict

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
#: metric name -> its key in ``MethodRow.per_split``; the others are pooled over the splits.
SPLIT_METRICS = {**{f"R@{k}": f"recall@{k}" for k in (1, 3, 5, 10)}, "accepted": "accepted",
                 "precision": "precision", "unknown rejected": "unknown_rejection",
                 "own-traversal top-1": "own_traversal"}
#: What a precision–recall number is: one curve of every split's queries.
POOLED = "pooled over the splits"
#: The settings that choose a run's splits (``evaluation.draw_splits``), by protocol.
SPLIT_SETTINGS = {
    Protocol.PAPER.value: ("dataset", "places", "group", "step", "reading", "runs", "seed"),
    Protocol.OPEN_SET.value: ("dataset", "places", "group", "step", "reading", "runs", "seed", "unknown_share"),
    Protocol.TRAVERSAL.value: ("dataset", "places", "group", "step", "reading", "database", "queries"),
    Protocol.DATABASE.value: ("dataset", "places", "group", "step", "reading", "database", "queries"),
}


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

    def splits(self, metric: str, key: str) -> np.ndarray | None:
        """``(n_splits,)`` one metric of one method split by split (NaN where a split leaves it undefined).

        ``None`` for a metric pooled over the splits (precision–recall), a method or metric the
        run does not have, or a run recorded without its per-split values.
        """
        name = SPLIT_METRICS.get(metric)
        row = next((r for r in self.evaluation.rows if r.key == key), None)
        if name is None or row is None or name not in row.per_split:
            return None
        return np.asarray(row.per_split[name], dtype=np.float64)

    def summary(self, metric: str, key: str) -> paired.Summary:
        """mean ± std and the 95% interval over the splits (``paired.summary``).

        A pooled metric, or a run without per-split values, is its one number (``n`` = 1, its
        note saying which); a metric the run does not have is ``paired.NO_SUMMARY``.
        """
        values = self.splits(metric, key)
        if values is not None:
            s = paired.summary(values)
            one_run = self.settings.get("protocol") in (Protocol.TRAVERSAL.value, Protocol.DATABASE.value)
            return paired.single(s.mean, "one run") if one_run and s.n == 1 else s
        value = self.value(metric, key)
        if math.isnan(value):
            return paired.NO_SUMMARY
        return paired.single(value, POOLED if metric not in SPLIT_METRICS else "no per-split values")


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


#: The largest runs file read (a bench of many datasets × descriptors writes a few MB).
MAX_RUN_FILE_BYTES = 64 * 2**20


def read_run_file(path: Path) -> tuple[list[RunRecord], list[str]]:
    """The runs of a file, to keep beside the session's: a runs export (``runs_json``, the Evaluation page's
    **Download runs (JSON)**) or the ``bench.json`` of ``vpr-explorer bench`` (one run per cell that ran).

    Each record keeps the file's name and settings (a bench cell: ``dataset · descriptor · protocol``, its
    evaluation's settings with the descriptor); its id is empty: ``add_runs`` gives each one. A bench cell that
    failed has no numbers: it is left out and said in the notes, as are cells and runs already in the file twice.
    JSON only, nothing in it is executed.

    Raises:
        VPRInputError: the file cannot be read, is too large, is not JSON, or is neither kind of file (naming it).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_RUN_FILE_BYTES:
            raise VPRInputError(f"{path}: {size / 2**20:.0f} MiB, more than a runs file holds "
                                f"({MAX_RUN_FILE_BYTES // 2**20} MiB): open a runs .json or a bench's bench.json")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise VPRInputError(f"{path}: cannot be read ({exc}); give a runs .json or a bench's bench.json") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise VPRInputError(f"{path}: not JSON ({exc}); give a runs .json or a bench's bench.json") from None
    notes: list[str] = []
    found: list[RunRecord] = []
    try:
        if isinstance(data, dict) and isinstance(data.get("runs"), list):
            for r in data["runs"]:
                found.append(RunRecord("", str(r["name"]), dict(r["settings"]), Evaluation.from_dict(r["evaluation"]),
                                       bool(r.get("pinned", False))))
        elif isinstance(data, dict) and isinstance(data.get("cells"), list) and "settings" in data:
            for c in data["cells"]:
                where = f"{c['dataset']} · {c['descriptor']} · {c.get('protocol') or '—'}"
                if c.get("evaluation") is None:
                    notes.append(f"{where}: failed in the bench ({c.get('error')}), no numbers to show")
                    continue
                ev = Evaluation.from_dict(c["evaluation"])
                found.append(RunRecord("", where, run_settings(ev, {"descriptor": c["descriptor"]}), ev))
        else:
            raise VPRInputError(f"{path}: neither a runs export (a 'runs' list) nor a bench's bench.json "
                                "(a 'cells' list): give the file the Evaluation page's Download runs (JSON) or "
                                "vpr-explorer bench --out writes")
    except (KeyError, TypeError, AttributeError) as exc:
        raise VPRInputError(f"{path}: a run in it lacks {exc} or holds the wrong kind of value; give the file as "
                            "vpr-explorer wrote it") from None
    except VPRInputError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise VPRInputError(f"{path}: {exc}") from None
    return found, notes


def add_runs(runs: Sequence[RunRecord], new: Iterable[RunRecord], issued: int) -> tuple[tuple[RunRecord, ...], int]:
    """``runs`` with each of ``new`` added by ``add_run`` under a fresh id (``next_id``), and the last number issued.

    A run whose settings a kept run has is not added again.
    """
    out = tuple(runs)
    for r in new:
        if find_run(out, r.settings) is not None:
            continue
        run_id = next_id(out, issued)
        issued = int(run_id.split()[-1])
        out = add_run(out, dataclasses.replace(r, id=run_id))
    return out, issued


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
    ref, keys = _checked(runs, metrics, methods, reference)
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


def same_splits(run: RunRecord, other: RunRecord) -> tuple[bool, str]:
    """Whether two runs scored the same splits (module doc), and in words why not.

    Read from the recorded settings: the protocol, then the settings that choose its
    splits (``SPLIT_SETTINGS``). Returns ``(True, "")`` or ``(False, "seed 0 vs 1")`` (every
    setting that differs, ``;``-separated).
    """
    p, q = run.settings.get("protocol"), other.settings.get("protocol")
    if p != q:
        return False, f"protocol {p} vs {q}"
    differ = [f"{k} {run.settings.get(k, '—')} vs {other.settings.get(k, '—')}"
              for k in SPLIT_SETTINGS.get(str(p), SPLIT_SETTINGS[Protocol.PAPER.value])
              if str(run.settings.get(k)) != str(other.settings.get(k))]
    return (not differ), "; ".join(differ)


def _pooled_difference(a: float, b: float, is_paired: bool, why: str, tag: str) -> paired.Difference:
    nan = math.nan
    return paired.Difference(is_paired, 1, a - b, nan, nan, nan, nan, nan, nan, why, tag)


def difference(run: RunRecord, reference: RunRecord, metric: str, key: str) -> paired.Difference:
    """One metric of one method, ``run`` − ``reference``: paired on the same splits, else Welch's (module doc).

    A pooled metric (or runs without per-split values) is the difference of the two numbers,
    with no interval and no test, its note saying so; NaN where either run lacks it.
    """
    same, why = same_splits(run, reference)
    a, b = run.splits(metric, key), reference.splits(metric, key)
    if a is None or b is None:
        note = POOLED if metric not in SPLIT_METRICS else "no per-split values"
        tag = "pooled, no test" if metric not in SPLIT_METRICS else "no test"
        if not same:
            note, tag = f"{paired.SPLITS_DIFFER} ({why}); {note}", f"{tag}, {paired.SPLITS_DIFFER}"
        return _pooled_difference(run.value(metric, key), reference.value(metric, key), same,
                                  f"{note}: no interval, no test", tag)
    if same and len(a) == len(b):
        return _one_run(run, paired.paired(a, b))
    why = why or f"{len(a)} vs {len(b)} splits"
    d = paired.welch(a, b)
    return dataclasses.replace(d, note=d.note.replace(paired.SPLITS_DIFFER, f"{paired.SPLITS_DIFFER} ({why})", 1))


def method_difference(run: RunRecord, metric: str, key: str, other: str) -> paired.Difference:
    """One metric of two methods of one run, ``key`` − ``other``: always paired (one run's splits)."""
    a, b = run.splits(metric, key), run.splits(metric, other)
    if a is None or b is None:
        note = POOLED if metric not in SPLIT_METRICS else "no per-split values"
        return _pooled_difference(run.value(metric, key), run.value(metric, other), True,
                                  f"{note}: no interval, no test",
                                  "pooled, no test" if metric not in SPLIT_METRICS else "no test")
    return _one_run(run, paired.paired(a, b))


def _one_run(run: RunRecord, d: paired.Difference) -> paired.Difference:
    """``d`` of a one-run protocol (traversal, database/queries) said as such rather than as one split."""
    if d.n == 1 and run.settings.get("protocol") in (Protocol.TRAVERSAL.value, Protocol.DATABASE.value):
        return dataclasses.replace(d, note="one run: no interval, no test", tag="one run")
    return d


def _checked(runs: Sequence[RunRecord], metrics: Sequence[str], methods: Sequence[str] | None,
             reference: str | None) -> tuple[RunRecord, list[str]]:
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
    return ref, keys


def metric_stats(runs: Sequence[RunRecord], metrics: Sequence[str] = DEFAULT_METRICS, *,
                 methods: Sequence[str] | None = None, reference: str | None = None) -> list[dict[str, object]]:
    """``metric_table``'s cells over splits: each run's ``paired.Summary``, each difference's ``paired.Difference``.

    Rows and columns as ``metric_table`` (the same keys, in the same order); a run's cell is
    ``RunRecord.summary``, a difference column ``difference(run, reference, …)``.
    """
    ref, keys = _checked(runs, metrics, methods, reference)
    rows = []
    for key in keys:
        for metric in metrics:
            row: dict[str, object] = {"method": METHODS_BY_KEY[key].label, "key": key, "metric": metric}
            for r in runs:
                row[r.name] = r.summary(metric, key)
            for r in runs:
                if r.id != ref.id:
                    row[difference_column(r, ref)] = difference(r, ref, metric, key)
            rows.append(row)
    return rows


def method_differences(runs: Sequence[RunRecord], metrics: Sequence[str], key: str,
                       other: str) -> list[dict[str, object]]:
    """Two methods of each run compared split by split: one row per metric, one ``paired.Difference`` per run.

    Rows ``{"metric": name, "difference": "Δ <label> − <label>", <run name>: Difference, …}``.
    """
    for k in (key, other):
        if k not in METHODS_BY_KEY:
            raise VPRInputError(f"method {k!r}: choose from {', '.join(METHODS_BY_KEY)}")
    head = f"Δ {METHODS_BY_KEY[key].label} − {METHODS_BY_KEY[other].label}"
    return [{"metric": m, "difference": head, **{r.name: method_difference(r, m, key, other) for r in runs}}
            for m in metrics]


def splits_note(runs: Sequence[RunRecord], reference: str | None = None) -> list[str]:
    """For every run but the reference: whether its differences are paired, in one line each."""
    if not runs:
        return []
    ref = runs[_find(runs, reference)] if reference is not None else runs[0]
    lines = []
    for r in runs:
        if r.id == ref.id:
            continue
        same, why = same_splits(r, ref)
        lines.append(f"{r.name} − {ref.name}: " + ("the same splits, paired" if same
                                                   else f"{paired.SPLITS_DIFFER} ({why}): Welch's t-test, unpaired"))
    return lines


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


#: The columns ``runs_csv`` writes beside each metric's mean: ``"<metric> std"`` …
STAT_COLUMNS = ("std", "n", "ci95 low", "ci95 high")


def _stat_values(s: paired.Summary) -> list[object]:
    return [_csv_value(s.std), s.n if s.n and np.isfinite(s.mean) else "", _csv_value(s.low), _csv_value(s.high)]


def runs_csv(runs: Sequence[RunRecord], metrics: Sequence[str] = tuple(METRICS)) -> str:
    """One row per run and method: run id, name, pinned, every setting (columns), method key and label, each metric.

    Each metric is its mean, then ``"<metric> std"`` (ddof 1), ``"<metric> n"`` (the splits
    counted) and ``"<metric> ci95 low"`` / ``"… high"`` (the 95% t interval of the mean;
    ``paired.summary``); a pooled metric (precision–recall) has n = 1 and no std or
    interval. Rates in [0, 1]; a metric a run lacks is an empty cell.
    """
    names = setting_names(runs)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["run", "name", "pinned", *names, "method", "label",
                *(c for m in metrics for c in (m, *(f"{m} {x}" for x in STAT_COLUMNS)))])
    for r in runs:
        for row in r.evaluation.rows:
            values = []
            for m in metrics:
                values += [_csv_value(r.value(m, row.key)), *_stat_values(r.summary(m, row.key))]
            w.writerow([r.id, r.name, r.pinned, *(_csv_value(r.settings.get(k, "")) for k in names), row.key, row.label,
                        *values])
    return buf.getvalue()


def read_runs_csv(text: str) -> list[dict[str, object]]:
    """``runs_csv`` back: one dict per row, metrics and their statistics as floats (NaN for empty), the rest as text."""
    rows = list(csv.DictReader(io.StringIO(text)))
    numbers = {c for m in METRICS for c in (m, *(f"{m} {x}" for x in STAT_COLUMNS))}
    out = []
    for row in rows:
        parsed: dict[str, object] = dict(row)
        for c in numbers & set(row):
            parsed[c] = float(row[c]) if row[c] != "" else math.nan
        out.append(parsed)
    return out


def _to_dict(value: object) -> object:
    return value.to_dict() if isinstance(value, (paired.Summary, paired.Difference)) else value



def runs_json(runs: Sequence[RunRecord], metrics: Sequence[str] = DEFAULT_METRICS, *,
              reference: str | None = None) -> str:
    """Strict JSON (NaN as ``null``): every run with its settings and its whole ``Evaluation.to_dict()``, the
    comparison table of ``metrics`` against ``reference`` (means, then ``metric_stats``: mean ± std, intervals,
    differences with their p-values and whether they are paired), and every method's rates split by split."""
    ref = runs[_find(runs, reference)] if reference is not None and runs else (runs[0] if runs else None)
    data = {
        "setting_names": setting_names(runs),
        "differing_settings": differing_settings(runs),
        "runs": [{"id": r.id, "name": r.name, "pinned": r.pinned, "settings": dict(r.settings),
                  "evaluation": r.evaluation.to_dict()} for r in runs],
        "comparison": {"reference": None if ref is None else ref.id, "metrics": list(metrics),
                       "rows": metric_table(runs, metrics, reference=None if ref is None else ref.id) if runs else [],
                       "splits": splits_note(runs, None if ref is None else ref.id),
                       "statistics": [{k: _to_dict(v) for k, v in row.items()} for row in
                                      metric_stats(runs, metrics, reference=None if ref is None else ref.id)]
                       if runs else []},
        "per_split": [{"id": r.id, "methods": {row.key: dict(row.per_split) for row in r.evaluation.rows}}
                      for r in runs],
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
