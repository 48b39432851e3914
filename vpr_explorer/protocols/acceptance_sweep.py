"""The acceptance bench swept over one parameter: every rule's numbers at each value of it.

``sweep_bench`` runs ``protocols.acceptance.acceptance_report`` once per value of one
parameter (``Parameter``) and keeps, per value, each rule's authors' ``Counts`` on the closed
set and on the natural open set, its AUC-PR and its τ. The parameters, and the rules that read
each (``READERS``):

| parameter | what it is | read by |
|---|---|---|
| ``ds`` | SeqSLAM's sequence length (and the sequence place scores') | seqslam, sequence-per-place |
| ``patch`` | p of the per-query threshold (and so the graph matcher's cost) | per-query, per-query-graph |
| ``fanout`` | the graph matcher's fan-out | per-query-graph |
| ``sue_k`` | K of SUE | sue |
| ``reference_share`` | F of the natural open set | every rule, natural open set only |
| ``group``, ``step`` | the places (``places.retrieval_places``) | per-place, per-place-k, sequence-per-place |

**What is recomputed.** Every rule of the bench reads only its own parameters, so at each
value only the rules that read the parameter run again (``BenchOptions.rules`` cut to them);
the others run once, at the given options, and their numbers stand in every column. A rule's
numbers are those of the whole bench run at that value (``tests/test_acceptance_sweep.py``
checks every value against ``acceptance_report`` itself). ``reference_share`` reruns the
whole bench: it changes every rule's natural open set.

**Values** are checked as the bench checks them: ``BenchOptions`` for its fields, ``PlaceSpec``
(or ``MetricPlaceSpec``) for group and step, with their messages; a ``reference_share`` that
keeps fewer than 2 database images or all of them is refused as ``natural_open_set`` refuses
it; group/step values that give fewer than 2 places are refused as ``retrieval_places``
refuses them. A value given twice is run once; at most ``MAX_VALUES`` values.

**A parameter the value cannot use is refused by name, with why** (``check_parameter``): when
every rule that reads it is left out (by ``options.rules``, or as the bench leaves it out:
the sequence rules where the queries or the database are not one route in order, SUE without
positions in metres, the per-place rules without places), ``reference_share`` where the
database is not one route in order (no natural open set), and group/step where the places are
discovered online or given by the layout. A rule that reads the parameter and is left out at
one value only (e.g. SeqSLAM at an odd ``ds``) is left out there, with the reason, as the bench
does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceSpec, retrieval_places
from vpr_explorer.protocols.acceptance import (
    RULES,
    RULES_BY_KEY,
    AcceptanceReport,
    Bench,
    BenchOptions,
    Counts,
    PlaceSource,
    acceptance_report,
    metres_positions,
    sequence_reason,
)

#: Most values one sweep runs (each runs the rules that read the parameter once more).
MAX_VALUES = 32


class Parameter(StrEnum):
    """A parameter the sweep varies: a ``BenchOptions`` field, or group/step of the places."""

    DS = "ds"
    PATCH = "patch"
    FANOUT = "fanout"
    SUE_K = "sue_k"
    REFERENCE_SHARE = "reference_share"
    GROUP = "group"
    STEP = "step"


_PLACE_RULES = ("per-place", "per-place-k", "sequence-per-place")

#: parameter -> the rules whose numbers it changes
READERS: dict[Parameter, tuple[str, ...]] = {
    Parameter.DS: ("seqslam", "sequence-per-place"),
    Parameter.PATCH: ("per-query", "per-query-graph"),
    Parameter.FANOUT: ("per-query-graph",),
    Parameter.SUE_K: ("sue",),
    Parameter.REFERENCE_SHARE: tuple(r.key for r in RULES),
    Parameter.GROUP: _PLACE_RULES,
    Parameter.STEP: _PLACE_RULES,
}

#: what each parameter is, for tables and messages
DESCRIPTIONS: dict[Parameter, str] = {
    Parameter.DS: "SeqSLAM's sequence length (and the sequence place scores')",
    Parameter.PATCH: "patch p of the per-query threshold (and the graph matcher's non-matching cost)",
    Parameter.FANOUT: "the graph matcher's fan-out",
    Parameter.SUE_K: "K of SUE",
    Parameter.REFERENCE_SHARE: "F of the natural open set (the share of the database route kept)",
    Parameter.GROUP: "group of the group/step places",
    Parameter.STEP: "step of the group/step places",
}


@dataclass(frozen=True, eq=False)
class SetNumbers:
    """One set's numbers at one value (rule keys in ``RULES`` order).

    Attributes:
        counts: rule key -> the authors' counts.
        auc: rule key -> the area under its precision–recall curve (NaN where it has none).
        tau: rule key -> the τ it ran at (NaN for a rule with thresholds of its own).
        tau_note: rule key -> where τ came from (``RuleDecisions.tau_note``).
        left_out: rule key -> why it did not run.
    """

    counts: dict[str, Counts]
    auc: dict[str, float]
    tau: dict[str, float]
    tau_note: dict[str, str]
    left_out: dict[str, str]

    def to_dict(self) -> dict:
        rules = {k: {**c.to_dict(), "auc": _num(self.auc[k]), "tau": _num(self.tau[k]), "tau_note": self.tau_note[k]}
                 for k, c in self.counts.items()}
        return {"rules": rules, "left_out": dict(self.left_out)}


@dataclass(frozen=True, eq=False)
class SweepPoint:
    """The bench at one value of the parameter.

    Attributes:
        value: the parameter's value.
        closed: every rule on the whole database.
        natural: every rule on the natural open set, ``None`` where it was not run.
        natural_note: why the natural open set was not run (empty where it was).
    """

    value: int | float
    closed: SetNumbers
    natural: SetNumbers | None
    natural_note: str

    def to_dict(self) -> dict:
        return {"value": self.value, "closed_set": self.closed.to_dict(),
                "natural_open_set": None if self.natural is None else self.natural.to_dict(),
                "natural_open_set_note": self.natural_note}


@dataclass(frozen=True, eq=False)
class BenchSweep:
    """The bench at each value of one parameter (module doc).

    Attributes:
        parameter: the parameter varied.
        values: its values, in the order given (each once).
        recomputed: the rules run again at each value (``READERS`` among the rules asked for).
        points: one ``SweepPoint`` per value.
        settings: what shaped the numbers (``AcceptanceReport.settings``), the parameter's entry
            holding every value.
    """

    parameter: Parameter
    values: tuple[int | float, ...]
    recomputed: tuple[str, ...]
    points: tuple[SweepPoint, ...]
    settings: dict

    def to_dict(self) -> dict:
        """Strict-JSON-ready values (no NaN: a number that is not finite is ``None``)."""
        return {"parameter": self.parameter.value, "description": DESCRIPTIONS[self.parameter],
                "values": list(self.values), "recomputed": list(self.recomputed), "settings": self.settings,
                "points": [p.to_dict() for p in self.points]}


def _num(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


# --------------------------------------------------------------------------- checks


def check_parameter(dataset, parameter: str, options: BenchOptions | None = None, *, labels: np.ndarray | None = None,
                    places: PlaceSpec | MetricPlaceSpec | None = None,
                    database_xy: np.ndarray | None = None) -> tuple[Parameter, tuple[str, ...]]:
    """The parameter, and the rules it makes run again, where the bench on ``dataset`` reads it (module doc).

    Args:
        dataset: the ``data.layouts.RetrievalDataset`` the bench runs on.
        parameter: a ``Parameter`` value.
        options: the bench's other choices.
        labels: the group/step places the other values run with (``None``: none).
        places: the group/step spec whose group or step is varied (group/step only).
        database_xy: SUE's positions in metres where given (default ``metres_positions(dataset)``).

    Returns:
        ``(parameter, rules)``: the ``Parameter`` and the keys of the rules that read it, among
        those ``options.rules`` asks for, in ``RULES`` order.

    Raises:
        VPRInputError: a name that is not a ``Parameter``, or one the bench on ``dataset`` does
            not read (saying why).
    """
    options = BenchOptions() if options is None else options
    if parameter not in {p.value for p in Parameter}:
        raise VPRInputError(f"parameter={parameter!r}: the sweep varies one of {', '.join(p.value for p in Parameter)}")
    p = Parameter(parameter)
    wanted = options.rules or tuple(RULES_BY_KEY)
    readers = tuple(k for k in READERS[p] if k in wanted)
    if not readers:
        raise VPRInputError(f"{p} ({DESCRIPTIONS[p]}) is read by {', '.join(READERS[p])} only, and rules="
                            f"{list(options.rules)} leaves them out: add one of them or vary another parameter")
    if p is Parameter.REFERENCE_SHARE:
        if not dataset.ordered:
            raise VPRInputError(f"{p} cuts the natural open set at a share of the database route, and the database "
                                f"of {dataset.name!r} is not one route in order: the natural open set is not run")
        return p, readers
    if p in (Parameter.GROUP, Parameter.STEP):
        if options.places is PlaceSource.DISCOVERED:
            raise VPRInputError(f"{p} spaces the group/step places, and places='discovered' finds the places online "
                                "instead: vary it with places='group-step'")
        if dataset.database_place is not None:
            raise VPRInputError(f"{p} spaces the group/step places, and {dataset.name!r} gives its own places "
                                f"(the {dataset.layout.value} layout's place ids), which group/step do not change")
        if places is None:
            raise VPRInputError(f"{p}: give the group/step spec whose {p} is varied (places=PlaceSpec(group, step))")
    reasons = [why for why in (_left_out(dataset, k, options, labels, p, database_xy) for k in readers) if why]
    if len(reasons) == len(readers):
        raise VPRInputError(f"{p} ({DESCRIPTIONS[p]}) is read by {', '.join(readers)} only, which the bench leaves "
                            f"out here: {'; '.join(dict.fromkeys(reasons))}")
    return p, readers


def _left_out(dataset, key: str, options: BenchOptions, labels, parameter: Parameter, database_xy) -> str:
    """Why the bench leaves rule ``key`` out on ``dataset`` whatever the parameter's value ('' where it runs)."""
    rule = RULES_BY_KEY[key]
    if rule.needs == "sequence":
        why = sequence_reason(dataset)
        if why:
            return why
    if rule.needs == "positions" and database_xy is None:
        xy, why = metres_positions(dataset)
        if xy is None:
            return why
    grouped = options.places is PlaceSource.GROUP_STEP and parameter not in (Parameter.GROUP, Parameter.STEP)
    if key in _PLACE_RULES and grouped and labels is None:
        return "no places: give group/step labels or discovered places"
    return ""


def check_values(dataset, parameter: Parameter, values: Sequence, options: BenchOptions | None = None, *,
                 places: PlaceSpec | MetricPlaceSpec | None = None) -> tuple[int | float, ...]:
    """The values, each once in the order given, each refused as the bench refuses it (module doc).

    Returns:
        The values as plain ``int`` (``float`` for ``reference_share`` and metres).

    Raises:
        VPRInputError: no value, more than ``MAX_VALUES``, or a value the bench refuses, with
            its message (which names the parameter and the value).
    """
    options = BenchOptions() if options is None else options
    p = Parameter(parameter)
    values = values.tolist() if isinstance(values, np.ndarray) else values
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or not len(values):
        raise VPRInputError(f"{p}: give at least one value, e.g. {p}={getattr(options, p.value, 10)!r}")
    out: list[int | float] = []
    for v in values:
        if p in (Parameter.GROUP, Parameter.STEP):
            if places is None:
                raise VPRInputError(f"{p}: give the group/step spec whose {p} is varied (places=PlaceSpec(group, "
                                    "step))")
            _labels_at(dataset, places, p, v)
        else:
            replace(options, **{p.value: v})
            if p is Parameter.REFERENCE_SHARE:
                # natural_open_set's own rule, checked before any descriptor is read
                cut, nd = int(dataset.n_database * v), dataset.n_database
                if cut < 2 or cut >= nd:
                    raise VPRInputError(f"reference_share={v:g} keeps {cut} of {nd} database images: keep at least 2 "
                                        "and leave at least 1 out")
        v = float(v) if isinstance(v, (float, np.floating)) else int(v)
        if v not in out:
            out.append(v)
    if len(out) > MAX_VALUES:
        raise VPRInputError(f"{p}: {len(out)} values; a sweep runs the bench once per value: give at most "
                            f"{MAX_VALUES}")
    return tuple(out)


def _labels_at(dataset, places: PlaceSpec | MetricPlaceSpec, parameter: Parameter, value) -> np.ndarray:
    """The group/step places with ``parameter`` set to ``value`` (``retrieval_places``' refusals, named)."""
    spec = replace(places, **{parameter.value: value})
    try:
        labels, _ = (retrieval_places(dataset, None, spec) if isinstance(spec, MetricPlaceSpec)
                     else retrieval_places(dataset, spec))
    except VPRInputError as exc:
        raise VPRInputError(f"{parameter}={value!r}: {exc}") from None
    return labels


# --------------------------------------------------------------------------- the sweep


def sweep_bench(dataset, descriptors: np.ndarray, *, labels: np.ndarray | None, parameter: str, values: Sequence,
                options: BenchOptions | None = None, places: PlaceSpec | MetricPlaceSpec | None = None,
                settings: dict | None = None, database_xy: np.ndarray | None = None,
                progress: Callable[[int, int], None] | None = None) -> BenchSweep:
    """The bench at each value of one parameter (module doc).

    Args:
        dataset: a ``data.layouts.RetrievalDataset`` (as for ``acceptance_report``).
        descriptors: ``(n_images, D)`` unit descriptors in the value's order (database rows first).
        labels: ``(n_database,)`` group/step place of each database image (``-1`` between places),
            for every parameter but group and step, which make their own.
        parameter: a ``Parameter`` value.
        values: the parameter's values.
        options: the bench's other choices (the parameter's own field is not read).
        places: group/step only: the spec whose group or step is varied; a ``MetricPlaceSpec``
            varies metres.
        settings: what else shaped the numbers, copied into the settings.
        database_xy: SUE's positions in metres (default ``metres_positions(dataset)``).
        progress: called with ``(values done, values)`` after each value.

    Raises:
        VPRInputError: as ``check_parameter`` and ``check_values``, or as ``acceptance_report``.
    """
    options = BenchOptions() if options is None else options
    p, readers = check_parameter(dataset, parameter, options, labels=labels, places=places, database_xy=database_xy)
    values = check_values(dataset, p, values, options, places=places)
    wanted = options.rules or tuple(RULES_BY_KEY)
    others = tuple(k for k in wanted if k not in readers)
    base = None
    if others:
        base = acceptance_report(dataset, descriptors, labels=labels, options=replace(options, rules=others),
                                 settings=settings, database_xy=database_xy)
    points = []
    first: AcceptanceReport | None = None
    for i, v in enumerate(values):
        lab = labels
        if p in (Parameter.GROUP, Parameter.STEP):
            lab, at = _labels_at(dataset, places, p, v), replace(options, rules=readers)
        elif p is Parameter.REFERENCE_SHARE:
            at = replace(options, reference_share=v)
        else:
            at = replace(options, rules=readers, **{p.value: v})
        report = acceptance_report(dataset, descriptors, labels=lab, options=at, settings=settings,
                                   database_xy=database_xy)
        first = report if first is None else first
        closed = _merge(None if base is None else base.closed, report.closed)
        natural = None
        if report.natural is not None:
            natural = _merge(None if base is None else base.natural, report.natural)
        elif p is Parameter.REFERENCE_SHARE:
            raise VPRInputError(f"reference_share={v:g}: {report.natural_note}")
        points.append(SweepPoint(v, closed, natural, report.natural_note))
        if progress is not None:
            progress(i + 1, len(values))
    kept = {**first.settings, p.value: list(values)}
    if p in (Parameter.GROUP, Parameter.STEP):
        kept["group/step"] = f"{places.describe()}, {p} varied"
    return BenchSweep(p, values, readers, tuple(points), kept)


def _merge(base: Bench | None, bench: Bench) -> SetNumbers:
    """The rules of ``base`` beside those of ``bench`` (run at the value), in ``RULES`` order."""
    parts = [b for b in (base, bench) if b is not None]
    ran = {k: d for b in parts for k, d in b.decisions.items()}
    counts = {k: c for b in parts for k, c in b.counts.items()}
    left = {k: why for b in parts for k, why in b.left_out.items()}
    keys = [r.key for r in RULES if r.key in ran]
    return SetNumbers(counts={k: counts[k] for k in keys},
                      auc={k: float(ran[k].curve.auc) for k in keys},
                      tau={k: float(ran[k].tau) for k in keys},
                      tau_note={k: ran[k].tau_note for k in keys},
                      left_out={r.key: left[r.key] for r in RULES if r.key in left})


# --------------------------------------------------------------------------- the table


def cell(point: SweepPoint, key: str) -> str:
    """``"closed F1 / open F1 / rejection"`` of one rule at one value ("—" where not run or no distractor)."""
    c = point.closed.counts.get(key)
    o = None if point.natural is None else point.natural.counts.get(key)
    closed = "—" if c is None else f"{c.f1:.1f}"
    open_f1 = "—" if o is None else f"{o.f1:.1f}"
    rejection = "—" if o is None or o.rejection is None else f"{o.rejection:.1f}"
    return f"{closed} / {open_f1} / {rejection}"


def render(sweep: BenchSweep) -> str:
    """The sweep as a text table: rows = rules, columns = values, cells "closed F1 / open F1 / rejection"."""
    p = sweep.parameter
    s = sweep.settings
    share = s.get("reference_share")
    lines = [f"{s['dataset']}: {s['n_queries']:,} queries, {s['n_database']:,} database images; {p} varied "
             f"({DESCRIPTIONS[p]})"]
    keys = [r.key for r in RULES if any(r.key in pt.closed.counts for pt in sweep.points)]
    rows = []
    for key in keys:
        oracle = any(pt.closed.tau_note.get(key, "").startswith("oracle") for pt in sweep.points)
        mark = "* " if key in sweep.recomputed and p is not Parameter.REFERENCE_SHARE else "  "
        label = mark + RULES_BY_KEY[key].label + (" †" if oracle else "")
        rows.append((label, [cell(pt, key) for pt in sweep.points]))
    heads = [f"{p}={v:g}" for v in sweep.values]
    width = max([len(h) for h in heads] + [len(c) for _, cells in rows for c in cells]) + 3
    label_width = max([len(label) for label, _ in rows] + [6]) + 2
    head = f"{'rule':<{label_width}}" + "".join(f"{h:>{width}}" for h in heads)
    lines += [head, "-" * len(head)]
    lines += [f"{label:<{label_width}}" + "".join(f"{c:>{width}}" for c in cells) for label, cells in rows]
    lines.append("")
    open_what = ("the first F of the database route" if p is Parameter.REFERENCE_SHARE
                 else f"the first {share:.0%} of the database route" if isinstance(share, float) else "")
    lines.append(f"cells: closed-set F1 / natural open-set F1 ({open_what}) / rejection, percent, the authors' "
                 "counts; — : not run (or no distractor); † τ at the best F1 on these queries (oracle), at each "
                 "value")
    if p is Parameter.REFERENCE_SHARE:
        lines.append("reference_share cuts the natural open set: every rule's open F1 and rejection change with it, "
                     "its closed-set F1 does not")
    else:
        lines.append(f"* the rules that read {p}, run again at each value; the others do not read it and stand the "
                     "same in every column")
    lines += _left_out_lines(sweep)
    return "\n".join(lines)


def _left_out_lines(sweep: BenchSweep) -> list[str]:
    """A rule left out at every value, once; one left out at some values, per value."""
    out = []
    for r in RULES:
        whys = [pt.closed.left_out.get(r.key) for pt in sweep.points]
        if all(whys) and len(set(whys)) == 1:
            out.append(f"{r.key} left out: {whys[0]}")
            continue
        out += [f"{sweep.parameter}={v:g}: {r.key} left out: {why}" for v, why in zip(sweep.values, whys) if why]
    notes = [pt.natural_note for pt in sweep.points if pt.natural_note]
    if notes and len(notes) == len(sweep.points) and len(set(notes)) == 1:
        out.append(f"natural open set not run: {notes[0]}")
    return out
