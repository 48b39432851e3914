"""Group/step sweeps: one protocol over a grid of group × step, in both readings.

Each cell of the grid is a ``PlaceSpec(group, step, reading)`` evaluated with
``pipeline.run_protocol`` on the same descriptors, with the same options, exactly as one
``vpr-explorer evaluate`` of those settings would be (``tests/test_sweep.py`` checks every
cell against a separate run). Per cell:

* **R@1**: the place-level baseline's Recall@1 (mean over runs), the level every
  thresholded method ranks at;
* **gain**: a thresholded method's R@1 minus that baseline's (default the margin rule with
  the weighted θ_p, the paper's method): what the threshold adds at this group/step;
* **rejection**: the open set's unknown-place rejection of that method's family
  θ_p(k) = θ_p + k·s_p at one k (``evaluation._tradeoff``'s row of that k); closed-set
  protocols have no unknown places, so the cell says so instead of a number;
* **AUC**: the area under the method's precision–recall curve (``precision_recall``); a
  run that leaves the per-place curves out (the blocked paper pass on a large dataset)
  says so, and the place-level baseline's global-θ curve is there in every run.

What is shared between cells, and what is not:

* the descriptors are computed (or read from their cache) once, by the caller;
* the two readings name the same places whenever their periods agree: the skip reading's
  ``(group, step)`` is the stride reading's ``(group, group + step)``. A cell's places are
  keyed by their content (``frame_place``), so such a pair is evaluated once and the second
  cell carries the first's numbers (its settings restated);
* every evaluation is kept in a ``SweepCache`` keyed by the descriptors, the protocol's
  options and the places: a second sweep over an overlapping grid, or the same sweep with
  another metric shown, evaluates only the new cells;
* every image pair's score (``shared_scores.SharedScores``, up to ``SHARED_LIMIT`` images):
  the float32 similarity of all images that scores the queries, and a float64 Gram from
  which each split's negative statistics come pairwise. A split's μᵢ, σᵢ are still its own
  (its training images depend on group and step: the places, the query drawn from each, the
  held-out places), but they are sums over the Gram's rows, not a closed form
  of O(n·D²) per split. A run outside a sweep builds the same scores itself, so a cell and a
  separate ``evaluate`` agree bit for bit. Above the limit each cell fits its own in closed form.

A cell with no numbers says why (``Cell.empty``): the stride reading with ``step < group``
would overlap places; a group/step that leaves fewer than two places; a protocol that
refuses the places (the paper protocol needs two images per place, the open set three
places). Bad sweep settings (an empty list, a group of 0, an unknown protocol or method)
raise ``VPRInputError`` before any work.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import K_GRID, Evaluation, Progress, Protocol
from vpr_explorer.pipeline import check_finite, check_options, check_whole, run_protocol
from vpr_explorer.method.places import MAX_FRAMES, PlaceSpec, Reading, make_places
from vpr_explorer.protocols.precision_recall import GLOBAL_CURVE
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols.shared_scores import SharedScores

MAX_CELLS = 400
"""Most cells one sweep may hold (all readings together): each is a full protocol run."""
SWEEP_PROTOCOLS = (Protocol.PAPER, Protocol.TRAVERSAL, Protocol.OPEN_SET)
"""The protocols of aligned traversals, whose places group/step make."""
SWEEP_METHODS = ("margin-weighted", "margin-simple", "raw-weighted", "raw-simple")
"""The per-place thresholded methods a sweep can compare with the place-level baseline."""
BASELINE = "place-baseline"
LARGE_SWEEP_PAIRS = 10_000_000
"""Above this many image pairs a sweep is large: the app states its cost and waits for a button press.
A tenth of the Evaluation page's limit for one run (``traversal.AUTO_RUN_PAIRS``): a sweep is many runs, each
with its own negative statistics. Any sweep on Nordland_64x32 is above it (one traversal-protocol cell
scores 1.3e7 pairs); GardensPoint's 4 × 4 grid in both readings is below (2e6)."""
CACHE_ENTRIES = 512
"""Evaluations a ``SweepCache`` keeps (least recently used go first)."""


class Metric(StrEnum):
    """What a sweep cell reports (``Cell.value``)."""

    R1 = "r1"
    GAIN = "gain"
    REJECTION = "rejection"
    AUC = "auc"


METRIC_LABELS = {
    Metric.R1: "place-level R@1 (%)",
    Metric.GAIN: "gain in R@1 over the place level (points)",
    Metric.REJECTION: "unknown-place rejection at k (%)",
    Metric.AUC: "AUC of precision–recall",
}
METRIC_HELP = {
    Metric.R1: "Recall@1 of the place-level baseline (places ranked by raw_p, no threshold), mean over runs.",
    Metric.GAIN: "Recall@1 of the chosen thresholded method minus the place-level baseline's, in percentage points: "
                 "what the threshold adds at this group/step.",
    Metric.REJECTION: "Open set only: the share of queries of held-out places that the chosen method's θ_p + k·s_p "
                      "rejects, mean over runs.",
    Metric.AUC: "Area under the chosen method's precision–recall curve (trapezoids over recall; accepted and right "
                "is a true positive, accepted and wrong or of an unknown place a false positive).",
}


# --------------------------------------------------------------------------- settings


def _whole_list(name: str, values: Sequence[object]) -> tuple[int, ...]:
    values = list(values)
    if not values:
        raise VPRInputError(f"{name}: give at least one whole number of frames, e.g. 1 2 3 5")
    out = sorted({check_whole(name, v, low=1, high=MAX_FRAMES, why=" frames") for v in values})
    return tuple(out)


@dataclass(frozen=True)
class SweepSpec:
    """A sweep's settings: the grid, the protocol and its options, and what the cells report.

    Attributes:
        groups, steps: frames per place and between places (sorted, duplicates dropped).
        readings: ``stride`` and/or ``skip`` (``places.Reading``); a grid per reading.
        protocol: ``paper``, ``traversal`` or ``open-set``.
        method: the thresholded method whose gain, rejection and AUC the cells report.
        k: the k of θ_p + k·s_p whose unknown-place rejection the open set reports; it is
            added to ``k_grid`` when missing (so a cell equals ``evaluate --k`` of that grid).
        runs … k_grid: ``pipeline.run_protocol``'s options, as for ``evaluate``.
        pr: compute precision–recall (the AUC); off is faster and leaves AUC empty.
    """

    groups: tuple[int, ...]
    steps: tuple[int, ...]
    readings: tuple[Reading, ...] = (Reading.STRIDE, Reading.SKIP)
    protocol: Protocol = Protocol.PAPER
    method: str = "margin-weighted"
    k: float = 0.0
    runs: int = 50
    seed: int = 0
    cross_condition: bool = False
    unknown_share: float = 0.3
    database: tuple[str, ...] | None = None
    queries: str | None = None
    tolerance: int = 0
    user_theta: float | None = None
    k_grid: tuple[float, ...] = K_GRID
    pr: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", _whole_list("groups", self.groups))
        object.__setattr__(self, "steps", _whole_list("steps", self.steps))
        readings = [self.readings] if isinstance(self.readings, str) else list(self.readings)
        if not readings:
            raise VPRInputError("readings: give stride, skip or both")
        for r in readings:
            if r not in {x.value for x in Reading}:
                raise VPRInputError(f"reading {r!r}: choose {' or '.join(x.value for x in Reading)}")
        object.__setattr__(self, "readings", tuple(Reading(r) for r in dict.fromkeys(readings)))
        try:
            protocol = Protocol(self.protocol)
        except ValueError:
            protocol = None
        if protocol not in SWEEP_PROTOCOLS:
            runs = ", ".join(p.value for p in SWEEP_PROTOCOLS)
            raise VPRInputError(f"protocol {self.protocol!r}: a sweep runs {runs} "
                                "(the protocols whose places group/step make)")
        object.__setattr__(self, "protocol", protocol)
        if self.method not in SWEEP_METHODS:
            raise VPRInputError(f"method {self.method!r}: choose one of {', '.join(SWEEP_METHODS)}")
        k = check_finite("k", self.k, example="0, the paper's θ_p")
        object.__setattr__(self, "k", k)
        grid = tuple(float(x) for x in self.k_grid)
        if k not in grid:
            grid = tuple(sorted((*grid, k)))
        object.__setattr__(self, "k_grid", grid)
        if self.database is not None:
            object.__setattr__(self, "database", tuple(self.database))
        n = len(self.cells())
        if n > MAX_CELLS:
            raise VPRInputError(f"{len(self.groups)} groups × {len(self.steps)} steps × {len(self.readings)} "
                                f"readings = {n} cells: at most {MAX_CELLS} (each is a protocol run); "
                                "give fewer values")

    def cells(self) -> list[tuple[int, int, Reading]]:
        """Every ``(group, step, reading)`` of the grid, reading by reading, group by group."""
        return [(g, s, r) for r in self.readings for g in self.groups for s in self.steps]

    def options(self) -> dict:
        """The keyword options of ``pipeline.run_protocol`` (and ``check_options``) for this protocol."""
        o: dict = {"user_theta": self.user_theta, "tolerance": self.tolerance}
        if self.protocol is Protocol.TRAVERSAL:
            o.update(database=list(self.database) if self.database else None, queries=self.queries)
        else:
            o.update(runs=self.runs, seed=self.seed, cross_condition=self.cross_condition)
            if self.protocol is Protocol.OPEN_SET:
                o.update(unknown_share=self.unknown_share, k_grid=list(self.k_grid))
        return o

    def settings(self) -> dict:
        """Every setting that shapes the cells' numbers (the CSV's and JSON's columns)."""
        o = self.options()
        return {"protocol": self.protocol.value, "method": self.method,
                "k": self.k if self.protocol is Protocol.OPEN_SET else None, "pr": self.pr,
                "runs": o.get("runs"), "seed": o.get("seed"), "cross_condition": o.get("cross_condition"),
                "unknown_share": o.get("unknown_share"), "k_grid": o.get("k_grid"),
                "database": o.get("database"), "queries": o.get("queries"), "tolerance": self.tolerance,
                "theta": self.user_theta}


# --------------------------------------------------------------------------- cells


@dataclass(frozen=True, eq=False)
class Cell:
    """One group/step of a sweep and its numbers (rates in [0, 1]; NaN where ``empty`` or ``missing`` says why).

    Attributes:
        r1: place-level baseline R@1; gain: the method's R@1 minus it; rejection: unknown-place
            rejection at k (open set); auc: the method's precision–recall AUC.
        n_places: places of this group/step (0 when the spec itself is invalid).
        empty: why the cell has no numbers, or ``None``.
        missing: metric -> why that one number is absent (e.g. rejection in a closed set).
        same_as: the ``(group, step, reading)`` whose evaluation this cell shares (same places).
        seconds: time this cell took here (0 when shared or cached).
        cost: image pairs the protocol scores for this cell (``traversal.protocol_pairs``).
        evaluation: the full ``Evaluation`` behind the numbers (``None`` when empty).
    """

    group: int
    step: int
    reading: Reading
    n_places: int = 0
    r1: float = math.nan
    gain: float = math.nan
    rejection: float = math.nan
    auc: float = math.nan
    empty: str | None = None
    missing: dict[str, str] = field(default_factory=dict)
    same_as: tuple[int, int, str] | None = None
    cached: bool = False
    seconds: float = 0.0
    cost: int = 0
    evaluation: Evaluation | None = field(default=None, repr=False)

    @property
    def spec(self) -> tuple[int, int, str]:
        return (self.group, self.step, self.reading.value)

    def value(self, metric: Metric | str) -> float:
        return float(getattr(self, Metric(metric).value))

    def why(self, metric: Metric | str) -> str | None:
        """Why ``metric`` has no number in this cell, or ``None`` when it has one."""
        return self.empty or self.missing.get(Metric(metric).value)

    def to_dict(self) -> dict:
        def num(x):
            return float(x) if x is not None and np.isfinite(x) else None

        return {"group": self.group, "step": self.step, "reading": self.reading.value, "n_places": self.n_places,
                **{m.value: num(self.value(m)) for m in Metric}, "empty": self.empty, "missing": dict(self.missing),
                "same_as": None if self.same_as is None else dict(zip(("group", "step", "reading"), self.same_as)),
                "seconds": self.seconds, "cost_pairs": self.cost}


def cell_numbers(ev: Evaluation, method: str, k: float) -> tuple[dict[str, float], dict[str, str]]:
    """The four numbers of one evaluation (``Metric`` values), and why any of them is absent.

    R@1 are means over runs; the gain is the difference of the two means. The rejection is
    the open set's trade-off row of the method's family (its threshold and rule) at ``k``.
    """
    m = METHODS_BY_KEY[method]
    base = ev.row(BASELINE).recall[1][0]
    numbers = {"r1": base, "gain": ev.row(method).recall[1][0] - base, "rejection": math.nan, "auc": math.nan}
    missing: dict[str, str] = {}
    if ev.protocol is Protocol.OPEN_SET:
        series = f"θ_p(k) {m.threshold}"
        row = next((t for t in ev.tradeoff if t.series == series and t.rule == m.rule.value
                    and abs(t.param - k) <= 1e-12), None)
        if row is None:
            missing["rejection"] = f"k = {k:g} is not on the run's k grid"
        else:
            numbers["rejection"] = row.unknown_rejection[0]
    else:
        missing["rejection"] = f"the {ev.protocol.value} protocol has no unknown places: run the open-set protocol"
    if not ev.pr:
        missing["auc"] = "precision–recall was not computed (pr off)"
    else:
        pr = next((r for r in ev.pr if r.key == method), None)
        if pr is None:
            left = [n for n in ev.notes if "precision–recall" in n]
            missing["auc"] = (left[-1] if left else f"no precision–recall row for {method}") + \
                f"; the place-level baseline's {GLOBAL_CURVE!r} curve has one (method place-baseline)"
        else:
            numbers["auc"] = pr.auc
    for key, value in numbers.items():
        if key not in missing and not np.isfinite(value):
            missing[key] = "undefined in this run (no query counted)"
    return numbers, missing


def _restate(ev: Evaluation, spec: PlaceSpec, other: PlaceSpec) -> Evaluation:
    """``ev`` (run for ``other``) with its settings naming ``spec``: the same places, described in ``spec``'s words."""
    s = dict(ev.settings)
    s.update(group=spec.group, step=spec.step, reading=spec.reading.value)
    if isinstance(s.get("places"), str):
        s["places"] = s["places"].replace(other.describe(), spec.describe())
    return dataclasses.replace(ev, settings=s)


# --------------------------------------------------------------------------- the cache


class SweepCache:
    """Evaluations by (descriptors, dataset, protocol options, places content): a thread-safe LRU.

    One instance serves many sweeps (the app keeps one per server): a cell whose key is
    in it is not evaluated again. Failures (a ``VPRInputError`` for those places) are kept
    too, as their message.
    """

    def __init__(self, size: int = CACHE_ENTRIES) -> None:
        self.size = size
        self.items: OrderedDict[tuple, tuple[Evaluation | str, PlaceSpec]] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: tuple):
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
        return None

    def put(self, key: tuple, value) -> None:
        with self.lock:
            self.items[key] = value
            self.items.move_to_end(key)
            while len(self.items) > self.size:
                self.items.popitem(last=False)

    def __len__(self) -> int:
        return len(self.items)


def _places_key(frame_place: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(frame_place, dtype=np.int64).tobytes()).hexdigest()


def _freeze(value):
    return tuple(value) if isinstance(value, list) else value


# --------------------------------------------------------------------------- cost


@dataclass(frozen=True)
class SweepCost:
    """What a sweep will cost, said before it starts.

    Attributes:
        cells: cells in the grid; valid: those whose group/step make places;
        runs: distinct evaluations to run (valid cells, less those sharing places, less cached ones);
        pairs: image pairs those evaluations score (``traversal.protocol_pairs``, summed).
    """

    cells: int
    valid: int
    runs: int
    pairs: int
    n_images: int

    @property
    def large(self) -> bool:
        """More than ``LARGE_SWEEP_PAIRS`` pairs: the app asks before starting."""
        return self.pairs > LARGE_SWEEP_PAIRS

    def describe(self) -> str:
        head = f"{self.cells} cell{'s' if self.cells != 1 else ''}, {self.valid} with valid places"
        if not self.runs:
            return f"{head}, every protocol run already in memory"
        return (f"{head}, {self.runs} protocol run{'s' if self.runs != 1 else ''} to do on {self.n_images:,} images: "
                f"about {self.pairs:.2g} image pairs")


def _plan(dataset: Dataset, spec: SweepSpec):
    """Each cell's ``(group, step, reading, PlaceSpec | None, Places | None, why empty)``."""
    if dataset.prepared_places is not None:
        raise VPRInputError(f"{dataset.name!r} has places fixed by its file names (Place####_…): group/step do not "
                            "apply, so there is nothing to sweep; evaluate it with `vpr-explorer evaluate`")
    out = []
    for g, s, r in spec.cells():
        try:
            ps = PlaceSpec(g, s, r)
        except VPRInputError as exc:
            out.append((g, s, r, None, None, str(exc)))
            continue
        try:
            places = make_places(dataset, ps)
        except VPRInputError as exc:
            out.append((g, s, r, ps, None, str(exc)))
            continue
        out.append((g, s, r, ps, places, None))
    return out


def sweep_cost(dataset: Dataset, spec: SweepSpec, *, cache: SweepCache | None = None,
               descriptors_key: str | None = None) -> SweepCost:
    """The cost of ``sweep(dataset, …, spec)`` before running it (no descriptors needed).

    With ``cache`` and ``descriptors_key``, cells already in the cache are not counted.
    """
    from vpr_explorer.views.traversal import protocol_pairs

    plan = _plan(dataset, spec)
    o = spec.options()
    seen: set[str] = set()
    runs = pairs = valid = 0
    for g, s, r, ps, places, why in plan:
        if places is None:
            continue
        valid += 1
        pk = _places_key(places.frame_place)
        if pk in seen:
            continue
        seen.add(pk)
        if cache is not None and descriptors_key is not None and \
                cache.get(_cache_key(descriptors_key, dataset, spec, pk)) is not None:
            continue
        runs += 1
        pairs += protocol_pairs(spec.protocol.value, places, dataset, runs=spec.runs, database=o.get("database"),
                                unknown_share=spec.unknown_share)
    return SweepCost(cells=len(plan), valid=valid, runs=runs, pairs=int(pairs), n_images=dataset.n_images)


def _cache_key(descriptors_key: str, dataset: Dataset, spec: SweepSpec, places_key: str) -> tuple:
    options = tuple(sorted((k, _freeze(v)) for k, v in spec.options().items()))
    return (descriptors_key, str(dataset.root), dataset.name, dataset.n_images, spec.protocol.value, options,
            spec.pr, places_key)


# --------------------------------------------------------------------------- the sweep


@dataclass(frozen=True, eq=False)
class SweepResult:
    """A sweep's cells, with its settings and the data it ran on.

    ``source`` is what the settings record of a descriptor file (its path and sha256,
    ``ImportedDescriptors.settings``); empty for an extractor's descriptors.
    """

    spec: SweepSpec
    cells: tuple[Cell, ...]
    dataset: str
    descriptor: str
    n_images: int
    seconds: float
    source: dict[str, str] = field(default_factory=dict)

    def cell(self, group: int, step: int, reading: Reading | str) -> Cell:
        want = (group, step, Reading(reading).value)
        return next(c for c in self.cells if c.spec == want)

    def grid(self, metric: Metric | str, reading: Reading | str) -> np.ndarray:
        """``(n_groups, n_steps)`` values of ``metric`` in one reading (rows: ``spec.groups``), NaN where empty."""
        z = np.full((len(self.spec.groups), len(self.spec.steps)), np.nan)
        for c in self.cells:
            if c.reading is Reading(reading):
                z[self.spec.groups.index(c.group), self.spec.steps.index(c.step)] = c.value(metric)
        return z

    def best(self, metric: Metric | str) -> Cell | None:
        """The cell with the highest ``metric`` (the first in grid order on a tie), or ``None``."""
        ok = [c for c in self.cells if np.isfinite(c.value(metric))]
        return max(ok, key=lambda c: c.value(metric)) if ok else None

    def settings(self) -> dict:
        return {"dataset": self.dataset, "descriptor": self.descriptor, **self.source, **self.spec.settings()}

    def to_dict(self) -> dict:
        """JSON-ready: every setting, then one entry per cell (rates in [0, 1], ``None`` where empty)."""
        return {"settings": self.settings(), "groups": list(self.spec.groups), "steps": list(self.spec.steps),
                "readings": [r.value for r in self.spec.readings], "seconds": self.seconds,
                "metrics": {m.value: METRIC_LABELS[m] for m in Metric},
                "cells": [c.to_dict() for c in self.cells]}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False)

    def to_csv(self) -> str:
        """One row per cell, every setting in its own column beside the cell's numbers."""
        settings = self.settings()
        columns = [*settings, "reading", "group", "step", "n_places", *(m.value for m in Metric), "empty", "missing",
                   "same_as", "seconds", "cost_pairs"]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        w.writeheader()
        flat = {k: (" ".join(map(str, v)) if isinstance(v, (list, tuple)) else v) for k, v in settings.items()}
        for c in self.cells:
            d = c.to_dict()
            w.writerow({**flat, **{k: d[k] for k in ("reading", "group", "step", "n_places", "seconds", "cost_pairs")},
                        **{m.value: "" if d[m.value] is None else repr(d[m.value]) for m in Metric},
                        "empty": c.empty or "", "missing": "; ".join(f"{k}: {v}" for k, v in c.missing.items()),
                        "same_as": "" if c.same_as is None else " ".join(map(str, c.same_as))})
        return buf.getvalue()


def sweep(
    dataset: Dataset,
    descriptors: np.ndarray,
    spec: SweepSpec,
    *,
    descriptor: str = "",
    descriptors_key: str | None = None,
    cache: SweepCache | None = None,
    progress: Progress | None = None,
    cell_progress: Progress | None = None,
    shared: SharedScores | None = None,
    source: dict[str, str] | None = None,
) -> SweepResult:
    """Evaluate every cell of ``spec``'s grid on ``dataset`` with ``descriptors`` (module doc).

    Args:
        descriptors: ``(n_images, D)`` L2-normalised, computed once by the caller.
        descriptor: its name, for the settings.
        source: for descriptors read from a file, its path and sha256 for the settings
            (``ImportedDescriptors.settings()``).
        descriptors_key: a content key of ``descriptors`` for ``cache`` (default their ``fingerprint``).
        cache: evaluations kept between sweeps; default a fresh one (within this sweep only).
        progress: ``progress(done, total, message)`` after each cell (``total`` = cells).
        cell_progress: the running cell's own protocol progress (its splits or blocks).
        shared: the ``SharedScores`` of ``descriptors`` to reuse (e.g. kept between sweeps);
            default one built for this sweep (its matrices on first use, and only up to
            ``shared_scores.SHARED_LIMIT`` images).

    Raises:
        VPRInputError: bad protocol options, a dataset whose places are fixed by file names, or
            descriptors that do not match the dataset. A cell's own refusal is its ``empty``.
    """
    t0 = time.perf_counter()
    check_options(spec.protocol, dataset, **spec.options())
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: "
                            "recompute them")
    from vpr_explorer.views.traversal import protocol_pairs

    if descriptors_key is None:
        from vpr_explorer.descriptors import fingerprint

        descriptors_key = fingerprint(descriptors)
    scores = SharedScores(descriptors) if shared is None else shared
    scores.check(descriptors)
    cache = SweepCache() if cache is None else cache
    plan = _plan(dataset, spec)
    o = spec.options()
    first_of: dict[str, PlaceSpec] = {}
    cells = []
    for i, (g, s, r, ps, places, why) in enumerate(plan):
        if places is None:
            cells.append(Cell(g, s, r, n_places=0, empty=why))
        else:
            pk = _places_key(places.frame_place)
            key = _cache_key(descriptors_key, dataset, spec, pk)
            cost = protocol_pairs(spec.protocol.value, places, dataset, runs=spec.runs, database=o.get("database"),
                                  unknown_share=spec.unknown_share)
            earlier = first_of.get(pk)  # a cell of the same places, evaluated before
            hit = cache.get(key)
            start = time.perf_counter()
            if hit is None:
                try:
                    value = run_protocol(spec.protocol, dataset, places, descriptors, progress=cell_progress,
                                         settings={"descriptor": descriptor, "dtype": str(descriptors.dtype)},
                                         pr=spec.pr, shared=scores, **o)
                except VPRInputError as exc:
                    value = str(exc)
                hit = (value, ps)
                cache.put(key, hit)
                cached = False
            else:
                cached = earlier is None
            value, ran_as = hit
            seconds = 0.0 if (cached or earlier is not None) else time.perf_counter() - start
            first_of.setdefault(pk, ps)
            same_as = None
            if earlier is not None:
                same_as = (earlier.group, earlier.step, earlier.reading.value)
            if isinstance(value, str):
                cells.append(Cell(g, s, r, n_places=places.n_places, empty=value, same_as=same_as, cached=cached,
                                  seconds=seconds, cost=cost))
            else:
                ev = value if ran_as == ps else _restate(value, ps, ran_as)
                numbers, missing = cell_numbers(ev, spec.method, spec.k)
                cells.append(Cell(g, s, r, n_places=places.n_places, **numbers, missing=missing, same_as=same_as,
                                  cached=cached, seconds=seconds, cost=cost, evaluation=ev))
        if progress:
            progress(i + 1, len(plan), f"group {g}, step {s} ({r.value})")
    return SweepResult(spec, tuple(cells), dataset.name, descriptor, dataset.n_images, time.perf_counter() - t0,
                       dict(source or {}))


def table(result: SweepResult, metric: Metric | str, reading: Reading | str) -> str:
    """One reading's grid of ``metric`` as text: groups down, steps across; "—" for an empty cell."""
    metric, reading = Metric(metric), Reading(reading)
    z = result.grid(metric, reading)
    scale = 1.0 if metric is Metric.AUC else 100.0
    fmt = "{:.3f}" if metric is Metric.AUC else "{:+.1f}" if metric is Metric.GAIN else "{:.1f}"
    header = ["group \\ step", *map(str, result.spec.steps)]
    rows = [[str(g), *("—" if not np.isfinite(v) else fmt.format(scale * v) for v in z[i])]
            for i, g in enumerate(result.spec.groups)]
    widths = [max(len(h), *(len(row[j]) for row in rows)) for j, h in enumerate(header)]
    line = lambda cells: "  ".join(c.ljust(w) if j == 0 else c.rjust(w) for j, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([f"{METRIC_LABELS[metric]}, {reading.value} reading", line(header),
                      "  ".join("-" * w for w in widths), *map(line, rows)])


def empty_reasons(result: SweepResult) -> list[str]:
    """Why cells are empty, one line per distinct reason with the cells it applies to."""
    by: dict[str, list[str]] = {}
    for c in result.cells:
        if c.empty:
            by.setdefault(c.empty, []).append(f"{c.group}/{c.step} {c.reading.value}")
    return [f"{', '.join(where)}: {why}" for why, where in by.items()]


def missing_reasons(result: SweepResult) -> list[str]:
    """Why a metric is absent from cells that have numbers, one line per (metric, reason)."""
    by: dict[tuple[str, str], int] = {}
    for c in result.cells:
        if not c.empty:
            for m, why in c.missing.items():
                by[(m, why)] = by.get((m, why), 0) + 1
    return [f"{m} ({n} cell{'s' if n != 1 else ''}): {why}" for (m, why), n in by.items()]


# --------------------------------------------------------------------------- the heatmap


def sweep_figure(result: SweepResult, metric: Metric | str, reading: Reading | str, *,
                 marked: tuple[int, int] | None = None):
    """A Plotly heatmap of ``metric`` over group (rows) × step (columns) in one reading; click a cell to pick it.

    Plotly heatmaps emit no selection events in Streamlit (streamlit#8760), so a marker
    sits on every cell with numbers (``meta="cells"``, invisible, carrying the hover text),
    ``customdata`` = ``[group, step, reading]`` (``selected_cell``); empty cells get a
    marker without customdata (``meta="empty"``) whose hover says why. ``marked``: the
    (group, step) in use, outlined.
    """
    import plotly.graph_objects as go

    metric, reading = Metric(metric), Reading(reading)
    spec = result.spec
    z = result.grid(metric, reading)
    scale = 1.0 if metric is Metric.AUC else 100.0
    xs, ys = [str(s) for s in spec.steps], [str(g) for g in spec.groups]
    fmt = ".3f" if metric is Metric.AUC else "+.1f" if metric is Metric.GAIN else ".1f"
    text = [["" if not np.isfinite(v) else format(scale * v, fmt) for v in row] for row in z]
    full = {"x": [], "y": [], "hover": [], "data": []}
    empty = {"x": [], "y": [], "hover": []}
    for i, g in enumerate(spec.groups):
        for j, s in enumerate(spec.steps):
            c = result.cell(g, s, reading)
            why = c.why(metric)
            where = f"group {g}, step {s} ({c.n_places} places)" if c.n_places else f"group {g}, step {s}"
            if c.empty:
                empty["x"].append(xs[j])
                empty["y"].append(ys[i])
                empty["hover"].append(f"{where}: empty<br>{why}")
                continue
            full["x"].append(xs[j])
            full["y"].append(ys[i])
            full["data"].append([g, s, reading.value])
            full["hover"].append(f"{where}: " + (f"no number<br>{why}" if why else text[i][j]) + "<br>click to use it")
    gain = metric is Metric.GAIN
    finite = np.abs(z[np.isfinite(z)]) * scale
    bound = float(finite.max()) if gain and finite.size and finite.max() > 0 else None
    fig = go.Figure(go.Heatmap(
        z=z * scale, x=xs, y=ys, text=text, texttemplate="%{text}", hoverinfo="skip", meta="values",
        colorscale="RdBu" if gain else "Viridis", zmid=0 if gain else None,
        zmin=-bound if bound else None, zmax=bound if bound else None, xgap=2, ygap=2,
        colorbar=dict(title=dict(text=METRIC_LABELS[metric].replace(" (", "<br>(").replace(" over", "<br>over"),
                                 side="right")),
    ))
    size = 22
    fig.add_trace(go.Scatter(
        x=full["x"], y=full["y"], mode="markers", meta="cells", customdata=full["data"], text=full["hover"],
        hovertemplate="%{text}<extra></extra>", showlegend=False,
        marker=dict(size=size, color="rgba(0,0,0,0)", symbol="square"),
    ))
    fig.add_trace(go.Scatter(
        x=empty["x"], y=empty["y"], mode="markers", meta="empty", text=empty["hover"],
        hovertemplate="%{text}<extra></extra>", showlegend=False,
        marker=dict(size=size, color="rgba(0,0,0,0)", symbol="x-thin", line=dict(width=1, color="#999")),
    ))
    if marked is not None and marked[0] in spec.groups and marked[1] in spec.steps:
        j, i = spec.steps.index(marked[1]), spec.groups.index(marked[0])
        fig.add_shape(type="rect", x0=j - 0.5, x1=j + 0.5, y0=i - 0.5, y1=i + 0.5, xref="x", yref="y",
                      line=dict(color="#e4572e", width=3), name="marked")
    fig.update_layout(
        title=dict(text=f"{reading.value} reading", x=0.0, xanchor="left"),
        xaxis=dict(title="step (frames)", type="category", range=[-0.5, len(xs) - 0.5]),
        yaxis=dict(title="group (frames)", type="category", range=[-0.5, len(ys) - 0.5]),
        height=max(340, 120 + 56 * len(ys)), margin=dict(l=60, r=20, t=60, b=50),
        hovermode="closest",
    )
    return fig


def selected_cell(point) -> tuple[int, int, str] | None:
    """``(group, step, reading)`` of a clicked ``sweep_figure`` cell, from a selection point, else ``None``."""
    data = point.get("customdata") if hasattr(point, "get") else None
    if isinstance(data, dict):
        data = [data[k] for k in sorted(data, key=int)]
    if not isinstance(data, (list, tuple)) or len(data) != 3:
        return None
    try:
        return int(data[0]), int(data[1]), Reading(str(data[2])).value
    except ValueError:
        return None

