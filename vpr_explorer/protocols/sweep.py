"""Group/step sweeps: one protocol over a grid of group × step, in both readings.

Each cell of the grid is one set of places (``group``, ``step`` and a reading) evaluated on
the same descriptors with the same options, exactly as one ``vpr-explorer evaluate`` of
those settings would be (``tests/test_sweep.py`` checks every cell against a separate run).
What a cell runs depends on the data:

* aligned traversals (``traversals.Dataset``, descriptors in traversal order): the paper,
  traversal and open-set protocols (``pipeline.run_protocol``) on places of ``group`` frames
  every ``step`` frames (``places.make_places``);
* any other dataset value (``layouts.RetrievalDataset``, database rows first): the
  database/queries protocol (``pipeline.evaluate_retrieval``) on places of group/step over
  its database images in listed order (``geometry`` frames), or in metres along its route or
  over a square lattice (``route``, ``lattice``) where it has positions
  (``places.retrieval_places``). The protocols that need aligned traversals are refused by
  name there; places the layout names (prepared places, a manifest's place column) leave
  nothing to sweep.

The protocol runs come from ``stages``: ``vpr_explorer.pipeline`` itself, passed by the caller
(protocols sit below the pipeline in the data flow, which wires them to datasets). Per cell:

* **R@1**: the place-level baseline's Recall@1 (mean over runs), the level every
  thresholded method ranks at;
* **gain**: a thresholded method's R@1 minus that baseline's (default the margin rule with
  the weighted θ_p, the paper's method): what the threshold adds at this group/step;
* **rejection**: unknown-place rejection of that method: in the open set, its family
  θ_p(k) = θ_p + k·s_p at one k (``evaluation._tradeoff``'s row of that k); in the
  database/queries protocol, at θ_p (k = 0) over the queries with no positive; closed-set
  protocols have no unknown places, so the cell says so instead of a number;
* **AUC**: the area under the method's precision–recall curve (``precision_recall``); a
  run that leaves the per-place curves out (the blocked paper pass on a large dataset)
  says so, and the place-level baseline's global-θ curve is there in every run.

What is shared between cells, and what is not:

* the descriptors are computed (or read from their cache) once, by the caller;
* the two readings name the same places whenever their periods agree: the skip reading's
  ``(group, step)`` is the stride reading's ``(group, group + step)``. A cell's places are
  keyed by their content (the place of each frame or database image), so such a pair is
  evaluated once and the second cell carries the first's numbers (its settings restated);
* every evaluation is kept in a ``SweepCache`` keyed by the descriptors, the protocol's
  options and the places: a second sweep over an overlapping grid, or the same sweep with
  another metric shown, evaluates only the new cells;
* in the paper and open-set protocols, every image pair's score (``shared_scores.SharedScores``, up to
  ``SHARED_LIMIT`` images): the float32 similarity of all images that scores the queries,
  and a float64 Gram from which each split's negative statistics come pairwise. A split's
  μᵢ, σᵢ are still its own (its training images depend on group and step: the places, the
  query drawn from each, the held-out places), but they are sums over the Gram's rows, not
  a closed form of O(n·D²) per split. A run outside a sweep builds the same scores itself,
  so a cell and a separate ``evaluate`` agree bit for bit. Above the limit each cell fits
  its own in closed form.

**Over splits** (``paired`` states the formulas). The paper and open-set protocols score
``runs`` random splits, every cell the same seed: each cell keeps its numbers split by split
(``Cell.stats``): R@1 and the rejection as mean ± std (ddof 1) over the splits with the 95%
Student-t interval of the mean (``paired.summary``); the gain as the paired comparison of the
method with the place-level baseline on the cell's splits (per-split differences, their mean,
its 95% interval and the paired t-test's p, ``paired.paired``; "identical on every split" when
the two agree in every split); the AUC is pooled over the splits (one number). The traversal
and database/queries protocols run once: one value, no interval. The CSV and JSON carry each
cell's std, interval and the gain's p; the heatmap's hover says them.

**One colour scale.** The heatmaps of one sweep compare: both readings of a metric share one
colour scale (``colour_range``), and R@1 and the rejection (both % of queries) share it too;
the gain's scale is symmetric about 0 (±its largest magnitude over both readings); the AUC's
spans its values over both readings.

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
from typing import Protocol as Interface

import numpy as np

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.data.traversals import Dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import (
    MetricPlaceSpec,
    PlaceGeometry,
    Places,
    PlaceSpec,
    Reading,
    make_places,
    retrieval_places,
)
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols import paired
from vpr_explorer.protocols.cost import protocol_pairs
from vpr_explorer.protocols.evaluation import Evaluation, Progress, Protocol
from vpr_explorer.protocols.options import K_GRID, RUNS, SEED, UNKNOWN_SHARE, check_finite
from vpr_explorer.protocols.precision_recall import GLOBAL_CURVE
from vpr_explorer.protocols.shared_scores import SharedScores

MAX_CELLS = 400
"""Most cells one sweep may hold (all readings together): each is a full protocol run."""
ALIGNED_PROTOCOLS = (Protocol.PAPER, Protocol.TRAVERSAL, Protocol.OPEN_SET)
"""The protocols of aligned traversals, whose places group/step make of their frames."""
SWEEP_PROTOCOLS = (*ALIGNED_PROTOCOLS, Protocol.DATABASE)
"""Every protocol a sweep runs: the aligned traversals' and the database/queries protocol of any other value."""
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
    Metric.REJECTION: "unknown-place rejection (%)",
    Metric.AUC: "AUC of precision–recall",
}
METRIC_HELP = {
    Metric.R1: "Recall@1 of the place-level baseline (places ranked by raw_p, no threshold), mean over runs.",
    Metric.GAIN: "Recall@1 of the chosen thresholded method minus the place-level baseline's, in percentage points: "
                 "what the threshold adds at this group/step.",
    Metric.REJECTION: "The share of queries of unknown places that the chosen method rejects: in the open set, the "
                      "queries of held-out places under θ_p + k·s_p (mean over runs); in the database/queries "
                      "protocol, the queries with no positive under θ_p (k = 0).",
    Metric.AUC: "Area under the chosen method's precision–recall curve (trapezoids over recall; accepted and right "
                "is a true positive, accepted and wrong or of an unknown place a false positive).",
}


class Stages(Interface):
    """The pipeline's stages a sweep runs its cells with: the ``vpr_explorer.pipeline`` module is one."""

    def check_options(self, protocol: Protocol | str, dataset, **options) -> Protocol: ...

    def run_protocol(self, protocol: Protocol | str, dataset: Dataset, places: Places, descriptors: np.ndarray,
                     **options) -> Evaluation: ...

    def evaluate_retrieval(self, dataset: RetrievalDataset, descriptors: np.ndarray, **options) -> Evaluation: ...


# --------------------------------------------------------------------------- settings


def _grid_values(name: str, values: Sequence[object], geometry: PlaceGeometry) -> tuple[int | float, ...]:
    """``values`` sorted, each once: whole frames (``PlaceSpec``'s rule) or metres (``MetricPlaceSpec``'s)."""
    values = list(values)
    metres = geometry is not PlaceGeometry.FRAMES
    if not values:
        raise VPRInputError(f"{name}: give at least one " + ("distance in metres, e.g. 10 25 50" if metres else
                                                            "whole number of frames, e.g. 1 2 3 5"))
    for v in values:
        try:
            MetricPlaceSpec(v, v, geometry=geometry) if metres else PlaceSpec(v, v)
        except VPRInputError as exc:
            raise VPRInputError(f"{name}={v!r}: {str(exc).split(': ', 1)[1]}") from None
    return tuple(sorted({float(v) if metres else int(v) for v in values}))


@dataclass(frozen=True)
class SweepSpec:
    """A sweep's settings: the grid, the protocol and its options, and what the cells report.

    Attributes:
        groups, steps: per place and between places (sorted, duplicates dropped): frames, or
            metres when ``geometry`` is route or lattice.
        readings: ``stride`` and/or ``skip`` (``places.Reading``); a grid per reading.
        protocol: ``paper``, ``traversal``, ``open-set`` (aligned traversals) or
            ``database-queries`` (a dataset value).
        geometry: what group/step count (``places.PlaceGeometry``): frames (aligned traversals'
            frames, or a value's database images in listed order), or metres along the route or
            of a lattice (the database/queries protocol on a value with positions).
        method: the thresholded method whose gain, rejection and AUC the cells report.
        k: the k of θ_p + k·s_p whose unknown-place rejection the open set reports; it is
            added to ``k_grid`` when missing (so a cell equals ``evaluate --k`` of that grid).
        runs … k_grid: ``pipeline.run_protocol``'s options, as for ``evaluate``.
        pr: compute precision–recall (the AUC); off is faster and leaves AUC empty.
    """

    groups: tuple[int | float, ...]
    steps: tuple[int | float, ...]
    readings: tuple[Reading, ...] = (Reading.STRIDE, Reading.SKIP)
    protocol: Protocol = Protocol.PAPER
    geometry: PlaceGeometry = PlaceGeometry.FRAMES
    method: str = "margin-weighted"
    k: float = 0.0
    runs: int = RUNS
    seed: int = SEED
    cross_condition: bool = False
    unknown_share: float = UNKNOWN_SHARE
    database: tuple[str, ...] | None = None
    queries: str | None = None
    tolerance: int = 0
    user_theta: float | None = None
    k_grid: tuple[float, ...] = K_GRID
    pr: bool = True

    def __post_init__(self) -> None:
        try:
            geometry = PlaceGeometry(self.geometry)
        except ValueError:
            raise VPRInputError(f"geometry {self.geometry!r}: choose "
                                f"{', '.join(g.value for g in PlaceGeometry)}") from None
        object.__setattr__(self, "geometry", geometry)
        object.__setattr__(self, "groups", _grid_values("groups", self.groups, geometry))
        object.__setattr__(self, "steps", _grid_values("steps", self.steps, geometry))
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
            raise VPRInputError(f"protocol {self.protocol!r}: a sweep runs "
                                f"{', '.join(p.value for p in SWEEP_PROTOCOLS)}") from None
        object.__setattr__(self, "protocol", protocol)
        if geometry is not PlaceGeometry.FRAMES and protocol is not Protocol.DATABASE:
            raise VPRInputError(f"geometry {geometry.value}: the {protocol.value} protocol makes places of aligned "
                                "traversals' frames; sweep metres with the database-queries protocol")
        if protocol is Protocol.DATABASE and self.tolerance:
            raise VPRInputError(f"tolerance={self.tolerance}: the database-queries protocol reads which images are "
                                "right from the dataset's ground truth; leave tolerance at 0")
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

    @property
    def unit(self) -> str:
        """What group and step count: ``"frames"`` or ``"m"``."""
        return "frames" if self.geometry is PlaceGeometry.FRAMES else "m"

    def cells(self) -> list[tuple[int | float, int | float, Reading]]:
        """Every ``(group, step, reading)`` of the grid, reading by reading, group by group."""
        return [(g, s, r) for r in self.readings for g in self.groups for s in self.steps]

    def place_spec(self, group: int | float, step: int | float, reading: Reading) -> PlaceSpec | MetricPlaceSpec:
        """The places of one cell: a ``PlaceSpec`` (frames) or a ``MetricPlaceSpec`` (metres); ``VPRInputError``
        when they are not valid (overlapping places in the stride reading)."""
        if self.geometry is PlaceGeometry.FRAMES:
            return PlaceSpec(group, step, reading)
        return MetricPlaceSpec(group, step, reading, self.geometry)

    def options(self) -> dict:
        """The keyword options of ``pipeline.run_protocol`` (and ``check_options``) for this protocol."""
        if self.protocol is Protocol.DATABASE:
            return {"user_theta": self.user_theta}
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
        return {"protocol": self.protocol.value, "geometry": self.geometry.value, "method": self.method,
                "k": self.k if self.protocol is Protocol.OPEN_SET else None, "pr": self.pr,
                "runs": o.get("runs"), "seed": o.get("seed"), "cross_condition": o.get("cross_condition"),
                "unknown_share": o.get("unknown_share"), "k_grid": o.get("k_grid"),
                "database": o.get("database"), "queries": o.get("queries"), "tolerance": o.get("tolerance"),
                "theta": self.user_theta}


# --------------------------------------------------------------------------- cells


@dataclass(frozen=True, eq=False)
class Cell:
    """One group/step of a sweep and its numbers (rates in [0, 1]; NaN where ``empty`` or ``missing`` says why).

    Attributes:
        group, step: frames, or metres (``SweepSpec.geometry``).
        r1: place-level baseline R@1; gain: the method's R@1 minus it; rejection: unknown-place
            rejection (open set at k, database/queries at θ_p); auc: the method's precision–recall AUC.
        n_places: places of this group/step (0 when the spec itself is invalid).
        empty: why the cell has no numbers, or ``None``.
        missing: metric -> why that one number is absent (e.g. rejection in a closed set).
        same_as: the ``(group, step, reading)`` whose evaluation this cell shares (same places).
        seconds: time this cell took here (0 when shared or cached).
        cost: image pairs the protocol scores for this cell (``cost.protocol_pairs``).
        evaluation: the full ``Evaluation`` behind the numbers (``None`` when empty).
        stats: metric value -> its numbers over the splits (``cell_stats``): a ``paired.Summary``
            (r1, rejection, auc) or the gain's paired ``paired.Difference``; empty when ``empty``.
    """

    group: int | float
    step: int | float
    reading: Reading
    n_places: int = 0
    r1: float = math.nan
    gain: float = math.nan
    rejection: float = math.nan
    auc: float = math.nan
    empty: str | None = None
    missing: dict[str, str] = field(default_factory=dict)
    same_as: tuple[int | float, int | float, str] | None = None
    cached: bool = False
    seconds: float = 0.0
    cost: int = 0
    evaluation: Evaluation | None = field(default=None, repr=False)
    stats: dict[str, paired.Summary | paired.Difference] = field(default_factory=dict, repr=False)

    @property
    def spec(self) -> tuple[int | float, int | float, str]:
        return (self.group, self.step, self.reading.value)

    @property
    def n_splits(self) -> int:
        """The splits behind R@1 (the protocol's runs; 1 for the traversal and database/queries protocols)."""
        r1 = self.stats.get(Metric.R1.value)
        return r1.n if isinstance(r1, paired.Summary) else 0

    def spread(self, metric: Metric | str) -> str:
        """``metric`` over the splits in words, in the heatmap's unit: ``"68.5 ± 4.1 [95% 63.4, 73.6], 5 splits"``.

        The gain: ``"+3.5 [95% 1.2, 5.8], p = 0.012 (paired over 5 splits)"``; empty where the
        cell has no such number.
        """
        metric = Metric(metric)
        s = self.stats.get(metric.value)
        if s is None or not np.isfinite(s.mean):
            return ""
        scale, digits = (1.0, 3) if metric is Metric.AUC else (100.0, 1)
        if isinstance(s, paired.Difference):
            return s.text(scale, digits)
        text = s.text(scale, digits)
        return text if s.n < 2 else f"{text}, {s.n} splits"

    def value(self, metric: Metric | str) -> float:
        return float(getattr(self, Metric(metric).value))

    def why(self, metric: Metric | str) -> str | None:
        """Why ``metric`` has no number in this cell, or ``None`` when it has one."""
        return self.empty or self.missing.get(Metric(metric).value)

    def to_dict(self) -> dict:
        def num(x):
            return float(x) if x is not None and np.isfinite(x) else None

        spread = {}
        for m in SPREAD_METRICS:
            s = self.stats.get(m.value)
            spread.update({f"{m.value}_std": num(s.std) if s else None, f"{m.value}_ci95_low": num(s.low) if s else None,
                           f"{m.value}_ci95_high": num(s.high) if s else None})
        gain = self.stats.get(Metric.GAIN.value)
        return {"group": self.group, "step": self.step, "reading": self.reading.value, "n_places": self.n_places,
                **{m.value: num(self.value(m)) for m in Metric}, "n_splits": self.n_splits, **spread,
                "gain_p": num(gain.p) if gain else None, "gain_test": gain.note if gain else None,
                "empty": self.empty, "missing": dict(self.missing),
                "same_as": None if self.same_as is None else dict(zip(("group", "step", "reading"), self.same_as)),
                "seconds": self.seconds, "cost_pairs": self.cost}


#: The metrics a cell states with a spread over splits (std, interval); the AUC is pooled over them.
SPREAD_METRICS = (Metric.R1, Metric.GAIN, Metric.REJECTION)
#: ``Cell.to_dict``'s columns of those spreads, with the gain's test, in the CSV's order.
SPREAD_COLUMNS = ("n_splits", *(f"{m.value}_{x}" for m in SPREAD_METRICS for x in ("std", "ci95_low", "ci95_high")),
                  "gain_p", "gain_test")


def cell_numbers(ev: Evaluation, method: str, k: float) -> tuple[dict[str, float], dict[str, str]]:
    """The four numbers of one evaluation (``Metric`` values), and why any of them is absent.

    R@1 are means over runs; the gain is the difference of the two means. The rejection is
    the open set's trade-off row of the method's family (its threshold and rule) at ``k``,
    or the database/queries protocol's rejection of the queries with no positive (θ_p, k = 0).
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
    elif ev.protocol is Protocol.DATABASE:
        rejected = ev.row(method).unknown_rejection
        if rejected is None:
            missing["rejection"] = "every query has a positive: the dataset has no unknown-place query"
        else:
            numbers["rejection"] = rejected[0]
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


def cell_stats(ev: Evaluation, method: str, k: float) -> dict[str, paired.Summary | paired.Difference]:
    """``cell_numbers``' numbers over the splits (``Cell.stats``; module doc).

    R@1: ``paired.summary`` of the place-level baseline's per-split R@1; gain: ``paired.paired``
    of the method's and the baseline's per-split R@1 (the same splits); rejection: the
    summary of the open set's trade-off row at ``k`` split by split, or of the database/queries
    protocol's one run; AUC: one number pooled over the splits. A metric the run lacks is
    left out.
    """
    m = METHODS_BY_KEY[method]
    base, row = ev.row(BASELINE), ev.row(method)
    out: dict[str, paired.Summary | paired.Difference] = {}
    if "recall@1" in base.per_split:
        out[Metric.R1.value] = paired.summary(base.per_split["recall@1"])
        if "recall@1" in row.per_split:
            out[Metric.GAIN.value] = paired.paired(row.per_split["recall@1"], base.per_split["recall@1"])
    rejected = None
    if ev.protocol is Protocol.OPEN_SET:
        t = next((t for t in ev.tradeoff if t.series == f"θ_p(k) {m.threshold}" and t.rule == m.rule.value
                  and abs(t.param - k) <= 1e-12), None)
        rejected = None if t is None else t.per_split.get("unknown_rejection")
    elif ev.protocol is Protocol.DATABASE:
        rejected = row.per_split.get("unknown_rejection")
    if rejected is not None:
        out[Metric.REJECTION.value] = paired.summary(rejected)
    pr = next((r for r in ev.pr if r.key == method), None)
    if pr is not None and np.isfinite(pr.auc):
        out[Metric.AUC.value] = paired.single(pr.auc, "pooled over the splits")
    if ev.protocol in (Protocol.TRAVERSAL, Protocol.DATABASE):  # one deterministic run, not a random split
        out = {k: paired.single(v.mean, "one run") if isinstance(v, paired.Summary) and v.n == 1 and not v.note
               else dataclasses.replace(v, note=ONE_RUN, tag="one run") if isinstance(v, paired.Difference) else v
               for k, v in out.items()}
    return out


#: What a one-run protocol's gain says in place of an interval.
ONE_RUN = "one run: no interval, no test"


def _restate(ev: Evaluation, spec: PlaceSpec | MetricPlaceSpec, other: PlaceSpec | MetricPlaceSpec) -> Evaluation:
    """``ev`` (run for ``other``) with its settings naming ``spec``: the same places, described in ``spec``'s words."""
    s = dict(ev.settings)
    s.update({k: v for k, v in (("group", spec.group), ("step", spec.step), ("reading", spec.reading.value))
              if k in s})
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
        self.items: OrderedDict[tuple, tuple[Evaluation | str, PlaceSpec | MetricPlaceSpec]] = OrderedDict()
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


def _places_key(labels: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(labels, dtype=np.int64).tobytes()).hexdigest()


def _freeze(value):
    return tuple(value) if isinstance(value, list) else value


# --------------------------------------------------------------------------- cost


@dataclass(frozen=True)
class SweepCost:
    """What a sweep will cost, said before it starts.

    Attributes:
        cells: cells in the grid; valid: those whose group/step make places;
        runs: distinct evaluations to run (valid cells, less those sharing places, less cached ones);
        pairs: image pairs those evaluations score (``cost.protocol_pairs``, summed).
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


@dataclass(frozen=True, eq=False)
class _Planned:
    """One cell before it runs: its place spec and places (``None`` with ``why`` when it has none)."""

    group: int | float
    step: int | float
    reading: Reading
    spec: PlaceSpec | MetricPlaceSpec | None = None
    places: Places | None = None
    n_places: int = 0
    key: str = ""
    why: str | None = None


def check_data(dataset: Dataset | RetrievalDataset, spec: SweepSpec) -> None:
    """Refuse data the sweep's protocol cannot run on, or whose places group/step do not make.

    Raises:
        VPRInputError: an aligned traversals' protocol on another layout, the database/queries
            protocol on aligned traversals given as traversals, or places named by the layout.
    """
    if spec.protocol is Protocol.DATABASE:
        if not isinstance(dataset, RetrievalDataset):
            raise VPRInputError(f"protocol {spec.protocol.value}: give {dataset.name!r} as its database/queries "
                                "value (data.aligned.database_queries) with the descriptors in its order")
        if dataset.database_place is not None:
            raise VPRInputError(f"group/step do not apply: the {dataset.layout.value} layout of {dataset.name!r} "
                                "names its places, so there is nothing to sweep; evaluate it with "
                                "`vpr-explorer evaluate`")
        return
    if not isinstance(dataset, Dataset):
        raise VPRInputError(f"protocol {spec.protocol.value}: it needs aligned traversals (frame f of every traversal "
                            f"the same spot); {dataset.name!r} is a {dataset.layout.value} layout: sweep it with the "
                            f"{Protocol.DATABASE.value} protocol")
    if dataset.prepared_places is not None:
        raise VPRInputError(f"group/step do not apply: {dataset.name!r} names its places in its file names "
                            "(Place####_…), so there is nothing to sweep; evaluate it with `vpr-explorer evaluate`")


def _plan(dataset: Dataset | RetrievalDataset, spec: SweepSpec) -> list[_Planned]:
    """Each cell's place spec and places, or why it has none."""
    check_data(dataset, spec)
    out = []
    for g, s, r in spec.cells():
        try:
            ps = spec.place_spec(g, s, r)
        except VPRInputError as exc:
            out.append(_Planned(g, s, r, why=str(exc)))
            continue
        try:
            if isinstance(dataset, Dataset):
                places = make_places(dataset, ps)
                labels, n = places.frame_place, places.n_places
            else:
                places = None
                labels, n = (retrieval_places(dataset, metric=ps) if isinstance(ps, MetricPlaceSpec)
                             else retrieval_places(dataset, ps))
        except VPRInputError as exc:
            out.append(_Planned(g, s, r, ps, why=str(exc)))
            continue
        out.append(_Planned(g, s, r, ps, places, n, _places_key(labels)))
    return out


def _cost(dataset: Dataset | RetrievalDataset, spec: SweepSpec, cell: _Planned) -> int:
    o = spec.options()
    return protocol_pairs(spec.protocol.value, cell.places, dataset, runs=spec.runs, database=o.get("database"),
                          unknown_share=spec.unknown_share)


def _cache_key(descriptors_key: str, dataset: Dataset | RetrievalDataset, spec: SweepSpec, places_key: str) -> tuple:
    options = tuple(sorted((k, _freeze(v)) for k, v in spec.options().items()))
    truth = ((dataset.layout.value, dataset.ground_truth.description, dataset.n_database)
             if isinstance(dataset, RetrievalDataset) else ())
    return (descriptors_key, str(dataset.root), dataset.name, dataset.n_images, *truth, spec.protocol.value,
            spec.geometry.value, options, spec.pr, places_key)


def sweep_cost(dataset: Dataset | RetrievalDataset, spec: SweepSpec, *, cache: SweepCache | None = None,
               descriptors_key: str | None = None) -> SweepCost:
    """The cost of ``sweep(dataset, …, spec)`` before running it (no descriptors needed).

    With ``cache`` and ``descriptors_key``, cells already in the cache are not counted.

    Raises:
        VPRInputError: as ``check_data``.
    """
    plan = _plan(dataset, spec)
    seen: set[str] = set()
    runs = pairs = valid = 0
    for cell in plan:
        if cell.why is not None:
            continue
        valid += 1
        if cell.key in seen:
            continue
        seen.add(cell.key)
        if cache is not None and descriptors_key is not None and \
                cache.get(_cache_key(descriptors_key, dataset, spec, cell.key)) is not None:
            continue
        runs += 1
        pairs += _cost(dataset, spec, cell)
    return SweepCost(cells=len(plan), valid=valid, runs=runs, pairs=int(pairs), n_images=dataset.n_images)


# --------------------------------------------------------------------------- the sweep


@dataclass(frozen=True, eq=False)
class SweepResult:
    """A sweep's cells, with its settings and the data it ran on.

    ``source`` is what the settings record of where the descriptors came from: a file's path
    and sha256 (``ImportedDescriptors.settings``), or a hub extractor's ``--hub-*`` flags
    (``descriptors.hub.hub_settings``); empty for the other extractors.
    """

    spec: SweepSpec
    cells: tuple[Cell, ...]
    dataset: str
    descriptor: str
    n_images: int
    seconds: float
    source: dict[str, str] = field(default_factory=dict)

    def cell(self, group: int | float, step: int | float, reading: Reading | str) -> Cell:
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
        """One row per cell, every setting in its own column beside the cell's numbers and their spreads.

        Rates in [0, 1]: each metric's mean, then ``n_splits``, each of R@1, gain and rejection's
        ``_std`` (ddof 1) and ``_ci95_low`` / ``_ci95_high`` (the 95% t interval of the mean; the
        gain's is the paired one), the gain's paired p-value ``gain_p`` and its test in words.
        """
        settings = self.settings()
        columns = [*settings, "reading", "group", "step", "n_places", *(m.value for m in Metric), *SPREAD_COLUMNS,
                   "empty", "missing", "same_as", "seconds", "cost_pairs"]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        w.writeheader()
        flat = {k: (" ".join(map(str, v)) if isinstance(v, (list, tuple)) else v) for k, v in settings.items()}
        for c in self.cells:
            d = c.to_dict()
            w.writerow({**flat, **{k: d[k] for k in ("reading", "group", "step", "n_places", "seconds", "cost_pairs")},
                        **{m: "" if d[m] is None else repr(d[m]) if isinstance(d[m], float) else d[m]
                           for m in (*(m.value for m in Metric), *SPREAD_COLUMNS)},
                        "empty": c.empty or "", "missing": "; ".join(f"{k}: {v}" for k, v in c.missing.items()),
                        "same_as": "" if c.same_as is None else " ".join(map(str, c.same_as))})
        return buf.getvalue()


def _evaluate(stages: Stages, dataset: Dataset | RetrievalDataset, descriptors: np.ndarray, spec: SweepSpec,
              cell: _Planned, *, descriptor: str, shared: SharedScores | None, progress: Progress | None) -> Evaluation:
    """One cell's protocol run, as ``vpr-explorer evaluate`` of its settings runs it."""
    settings = {"descriptor": descriptor, "dtype": str(descriptors.dtype)}
    if spec.protocol is Protocol.DATABASE:
        metric = cell.spec if isinstance(cell.spec, MetricPlaceSpec) else None
        return stages.evaluate_retrieval(dataset, descriptors, spec=None if metric else cell.spec, metric=metric,
                                         user_theta=spec.user_theta, settings=settings, progress=progress, pr=spec.pr)
    return stages.run_protocol(spec.protocol, dataset, cell.places, descriptors, progress=progress, settings=settings,
                               pr=spec.pr, shared=shared, **spec.options())


def sweep(
    dataset: Dataset | RetrievalDataset,
    descriptors: np.ndarray,
    spec: SweepSpec,
    stages: Stages,
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
        dataset: aligned traversals (``traversals.Dataset``) for the paper, traversal and open-set
            protocols; a dataset value (``layouts.RetrievalDataset``) for the database/queries protocol.
        descriptors: ``(n_images, D)`` L2-normalised in ``dataset``'s image order, computed once by the caller.
        stages: the protocol runs (``vpr_explorer.pipeline``: its ``check_options``, ``run_protocol``
            and ``evaluate_retrieval``).
        descriptor: its name, for the settings.
        source: what the settings record of where the descriptors came from: a file's path and
            sha256 (``ImportedDescriptors.settings()``), or a hub extractor's flags
            (``descriptors.hub.hub_settings``).
        descriptors_key: a content key of ``descriptors`` for ``cache`` (default their ``fingerprint``).
        cache: evaluations kept between sweeps; default a fresh one (within this sweep only).
        progress: ``progress(done, total, message)`` after each cell (``total`` = cells).
        cell_progress: the running cell's own protocol progress (its splits or blocks).
        shared: the ``SharedScores`` of aligned traversals' ``descriptors`` to reuse (e.g. kept
            between sweeps); default one built for this sweep (its matrices on first use, and only
            up to ``shared_scores.SHARED_LIMIT`` images). Not read by the database/queries protocol.

    Raises:
        VPRInputError: bad protocol options, data the protocol does not run on (``check_data``),
            or descriptors that do not match the dataset. A cell's own refusal is its ``empty``.
    """
    t0 = time.perf_counter()
    check_data(dataset, spec)
    stages.check_options(spec.protocol, dataset, **spec.options())
    plan = _plan(dataset, spec)
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: "
                            "recompute them")
    if descriptors_key is None:
        from vpr_explorer.descriptors import fingerprint

        descriptors_key = fingerprint(descriptors)
    scores = None
    if spec.protocol is not Protocol.DATABASE:
        scores = SharedScores(descriptors) if shared is None else shared
        scores.check(descriptors)
    cache = SweepCache() if cache is None else cache
    first_of: dict[str, PlaceSpec | MetricPlaceSpec] = {}
    cells = []
    for i, cell in enumerate(plan):
        g, s, r = cell.group, cell.step, cell.reading
        if cell.why is not None:
            cells.append(Cell(g, s, r, n_places=0, empty=cell.why))
        else:
            key = _cache_key(descriptors_key, dataset, spec, cell.key)
            cost = _cost(dataset, spec, cell)
            earlier = first_of.get(cell.key)  # a cell of the same places, evaluated before
            hit = cache.get(key)
            start = time.perf_counter()
            if hit is None:
                try:
                    value = _evaluate(stages, dataset, descriptors, spec, cell, descriptor=descriptor, shared=scores,
                                      progress=cell_progress)
                except VPRInputError as exc:
                    value = str(exc)
                hit = (value, cell.spec)
                cache.put(key, hit)
                cached = False
            else:
                cached = earlier is None
            value, ran_as = hit
            seconds = 0.0 if (cached or earlier is not None) else time.perf_counter() - start
            first_of.setdefault(cell.key, cell.spec)
            same_as = None if earlier is None else (earlier.group, earlier.step, earlier.reading.value)
            if isinstance(value, str):
                cells.append(Cell(g, s, r, n_places=cell.n_places, empty=value, same_as=same_as, cached=cached,
                                  seconds=seconds, cost=cost))
            else:
                ev = value if ran_as == cell.spec else _restate(value, cell.spec, ran_as)
                numbers, missing = cell_numbers(ev, spec.method, spec.k)
                cells.append(Cell(g, s, r, n_places=cell.n_places, **numbers, missing=missing, same_as=same_as,
                                  cached=cached, seconds=seconds, cost=cost, evaluation=ev,
                                  stats=cell_stats(ev, spec.method, spec.k)))
        if progress:
            progress(i + 1, len(plan), f"group {g:g}, step {s:g} ({r.value})")
    return SweepResult(spec, tuple(cells), dataset.name, descriptor, dataset.n_images, time.perf_counter() - t0,
                       dict(source or {}))


def table(result: SweepResult, metric: Metric | str, reading: Reading | str) -> str:
    """One reading's grid of ``metric`` as text: groups down, steps across; "—" for an empty cell."""
    metric, reading = Metric(metric), Reading(reading)
    z = result.grid(metric, reading)
    scale = 1.0 if metric is Metric.AUC else 100.0
    fmt = "{:.3f}" if metric is Metric.AUC else "{:+.1f}" if metric is Metric.GAIN else "{:.1f}"
    header = [f"group \\ step ({result.spec.unit})", *(f"{s:g}" for s in result.spec.steps)]
    rows = [[f"{g:g}", *("—" if not np.isfinite(v) else fmt.format(scale * v) for v in z[i])]
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
            by.setdefault(c.empty, []).append(f"{c.group:g}/{c.step:g} {c.reading.value}")
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

#: Metrics in the same unit (% of queries) whose heatmaps share one colour scale.
SHARED_SCALE = (Metric.R1, Metric.REJECTION)


def _display_scale(metric: Metric) -> float:
    return 1.0 if metric is Metric.AUC else 100.0


def colour_range(result: SweepResult, metric: Metric | str) -> tuple[float, float] | None:
    """The one colour scale of ``metric``'s heatmaps, in their unit (``sweep_figure``): ``(zmin, zmax)``.

    Over every reading of the sweep; R@1 and the rejection (``SHARED_SCALE``) over both; the
    gain symmetric about 0 (±its largest magnitude, at least 1 point); a single value widened
    by 1 (0.01 for the AUC). ``None`` when no cell has a number.
    """
    metric = Metric(metric)
    group = SHARED_SCALE if metric in SHARED_SCALE else (metric,)
    z = np.concatenate([result.grid(m, r).ravel() * _display_scale(m) for m in group for r in result.spec.readings])
    z = z[np.isfinite(z)]
    if not z.size:
        return None
    if metric is Metric.GAIN:
        bound = max(float(np.abs(z).max()), 1.0)
        return -bound, bound
    low, high = float(z.min()), float(z.max())
    if high - low <= 0:
        pad = 0.01 if metric is Metric.AUC else 1.0
        low, high = low - pad, high + pad
    return low, high


def scale_note(result: SweepResult, metric: Metric | str) -> str:
    """The heatmaps' colour scale in words, for a caption: which heatmaps share it, and its range."""
    metric = Metric(metric)
    span = colour_range(result, metric)
    if span is None:
        return ""
    readings = "both readings share" if len(result.spec.readings) > 1 else "the heatmap has"
    fmt = "{:.3f}" if metric is Metric.AUC else "{:+.1f}" if metric is Metric.GAIN else "{:.1f}"
    unit = "" if metric is Metric.AUC else " points" if metric is Metric.GAIN else "%"
    what = {Metric.GAIN: ", symmetric about 0", Metric.AUC: ""}.get(
        metric, " (the same for R@1 and the rejection, both % of queries)")
    return f"One colour scale: {readings} it, {fmt.format(span[0])} to {fmt.format(span[1])}{unit}{what}."


def sweep_figure(result: SweepResult, metric: Metric | str, reading: Reading | str, *,
                 marked: tuple[int | float, int | float] | None = None,
                 zrange: tuple[float, float] | None = None):
    """A Plotly heatmap of ``metric`` over group (rows) × step (columns) in one reading; click a cell to pick it.

    Plotly heatmaps emit no selection events in Streamlit (streamlit#8760), so a marker
    sits on every cell with numbers (``meta="cells"``, invisible, carrying the hover text:
    the mean with its spread over the splits, ``Cell.spread``), ``customdata`` =
    ``[group, step, reading]`` (``selected_cell``); empty cells get a marker without
    customdata (``meta="empty"``) whose hover says why. ``marked``: the (group, step) in use,
    outlined. ``zrange``: the colour scale (default ``colour_range``: one scale for every
    reading, so the heatmaps of one sweep compare).
    """
    import plotly.graph_objects as go

    metric, reading = Metric(metric), Reading(reading)
    spec = result.spec
    z = result.grid(metric, reading)
    scale = _display_scale(metric)
    xs, ys = [f"{s:g}" for s in spec.steps], [f"{g:g}" for g in spec.groups]
    fmt = ".3f" if metric is Metric.AUC else "+.1f" if metric is Metric.GAIN else ".1f"
    text = [["" if not np.isfinite(v) else format(scale * v, fmt) for v in row] for row in z]
    full = {"x": [], "y": [], "hover": [], "data": []}
    empty = {"x": [], "y": [], "hover": []}
    for i, g in enumerate(spec.groups):
        for j, s in enumerate(spec.steps):
            c = result.cell(g, s, reading)
            why = c.why(metric)
            where = f"group {g:g}, step {s:g} {spec.unit}" + (f" ({c.n_places} places)" if c.n_places else "")
            if c.empty:
                empty["x"].append(xs[j])
                empty["y"].append(ys[i])
                empty["hover"].append(f"{where}: empty<br>{why}")
                continue
            full["x"].append(xs[j])
            full["y"].append(ys[i])
            full["data"].append([g, s, reading.value])
            full["hover"].append(f"{where}: " + (f"no number<br>{why}" if why else c.spread(metric) or text[i][j])
                                 + "<br>click to use it")
    gain = metric is Metric.GAIN
    span = colour_range(result, metric) if zrange is None else zrange
    fig = go.Figure(go.Heatmap(
        z=z * scale, x=xs, y=ys, text=text, texttemplate="%{text}", hoverinfo="skip", meta="values",
        colorscale="RdBu" if gain else "Viridis", zmid=0 if gain else None,
        zmin=span[0] if span else None, zmax=span[1] if span else None, xgap=2, ygap=2,
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
        xaxis=dict(title=f"step ({spec.unit})", type="category", range=[-0.5, len(xs) - 0.5]),
        yaxis=dict(title=f"group ({spec.unit})", type="category", range=[-0.5, len(ys) - 0.5]),
        height=max(340, 120 + 56 * len(ys)), margin=dict(l=60, r=20, t=60, b=50),
        hovermode="closest",
    )
    return fig


def selected_cell(point) -> tuple[int | float, int | float, str] | None:
    """``(group, step, reading)`` of a clicked ``sweep_figure`` cell, from a selection point, else ``None``.

    Group and step are whole numbers when they are (frames), else metres.
    """
    data = point.get("customdata") if hasattr(point, "get") else None
    if isinstance(data, dict):
        data = [data[k] for k in sorted(data, key=int)]
    if not isinstance(data, (list, tuple)) or len(data) != 3:
        return None
    try:
        group, step = (float(x) for x in data[:2])
        return (*(int(x) if x.is_integer() else x for x in (group, step)), Reading(str(data[2])).value)
    except (TypeError, ValueError):
        return None

