"""Many runs at once: every dataset × descriptor × protocol of one bench, and one table of them.

A bench (``BenchSpec``) names datasets, descriptors and protocols; :func:`run_bench` runs
every combination, a **cell**, exactly as one ``vpr-explorer evaluate`` of the same
settings with ``--pr`` would run it, so that a cell's numbers equal that run's:

* **aligned traversal folders** (and prepared places, and ``"demo"``): the paper, traversal
  or open-set protocol (``pipeline.run_protocol``) on places of ``group`` frames every
  ``step`` frames (``places.make_places``);
* **database/queries layouts** (``layouts.RetrievalDataset``): the database-queries protocol
  (``pipeline.evaluate_retrieval``), group/step counting database images in listed order
  (geometry ``frames``) or metres along its route or over a lattice (``route``,
  ``lattice``); by default ``route`` or ``lattice`` where it has positions (``route`` when
  the database is one route in order), else ``frames``, as ``evaluate`` chooses.

Protocols: ``protocols`` when given, every one on every dataset; by default each dataset
runs ``evaluate``'s default for its layout (``DEFAULT_PROTOCOL``: paper for aligned
traversals, database-queries otherwise).

Options: the protocol options (``PROTOCOL_OPTIONS``: runs, seed, cross_condition,
unknown_share, k_grid, database, queries) go to the protocols that read them and are left
at ``ProtocolOptions``' defaults for the others (a protocol does not read them, so its
numbers are the same); one given that no cell's protocol reads is refused. The dataset
options are given to every dataset, and a dataset that ``evaluate`` would refuse them for
fails its cells: ``radius`` and ``geometry`` apply to database/queries layouts, a
``tolerance`` other than 0 to aligned traversals; ``theta`` goes to every protocol. Every
cell computes precision–recall (``pr=True``). ``descriptor_options`` (a torch.hub model's
input size, arguments, normalisation) go to every ``hub:DIR[:ENTRY]`` descriptor, the others
take none; a hub descriptor's cells and descriptors step record them as the ``--hub-*`` flags
that give them (``descriptors.hub.hub_settings``: ``"hub_options": "--hub-arg KEY=VALUE --hub-size W H"``).

What is shared: each dataset is read once; each dataset × descriptor's descriptors are
extracted (through the descriptor cache: ``pipeline.dataset_descriptors``) or read from a
descriptor file (``pipeline.imported_descriptors``) once and reused by all its protocols,
which also share one ``shared_scores.SharedScores`` of aligned traversals' descriptors up
to ``SHARED_LIMIT`` images (the same numbers, bit for bit, as a run that builds its own).

Each descriptors step is measured (``DescriptorRun``):

* ``seconds``: wall-clock seconds of the extraction, or of the cache or file read;
* ``python_peak``: bytes, the peak of Python-tracked allocations during the step above
  those live at its start (``tracemalloc``: numpy arrays included; memory that torch or
  PIL allocate themselves is not tracked);
* ``rss_growth``: bytes the process's resident high-water mark (``getrusage`` ``ru_maxrss``)
  rose during the step: everything, torch included, but only what goes beyond the
  process's earlier peak (0 when the step stayed under it); ``None`` where ``resource``
  is missing (Windows);
* ``cached_images``: images of the step already in the descriptor cache (``None`` for a
  file).

A cell fails alone: a dataset that cannot be read, a descriptor that cannot be computed, a
protocol or option that does not apply to the dataset, each ``VPRInputError`` becomes the
message of the cells it stops (``BenchCell.error``) and the rest still run. Bad bench
settings (an unknown descriptor, protocol or method, a value out of range, an option no
protocol reads) raise ``VPRInputError`` before any work.

The table (``BenchResult.rows``): one row per cell and method (``methods``: default every
method of the cell's table, in its order): Recall@1/5/10 (mean and std over runs), AUC,
R@100P and max F1 of the method's precision–recall row, the unknown-place rejection where
the protocol has unknown queries, and its descriptors' seconds and memory; a failed cell is
one row with its message.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import time
import tracemalloc
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol as Interface

import numpy as np

from vpr_explorer.data.layouts import Layout, RetrievalDataset, radius_applies
from vpr_explorer.descriptors.hub import hub_settings
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec, Reading, make_places
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols.evaluation import Evaluation, Progress, Protocol, recall_over_every_query, strict
from vpr_explorer.protocols.options import K_GRID, RUNS, SEED, UNKNOWN_SHARE, ProtocolOptions
from vpr_explorer.protocols.shared_scores import SHARED_LIMIT, SharedScores

#: ``evaluate``'s protocol for a dataset when none is named: paper for aligned traversals, database-queries otherwise
DEFAULT_PROTOCOL = {False: Protocol.PAPER, True: Protocol.DATABASE}
#: the protocols of aligned traversal folders
ALIGNED_PROTOCOLS = (Protocol.PAPER, Protocol.TRAVERSAL, Protocol.OPEN_SET)
#: protocol option (a ``ProtocolOptions`` field) -> the protocols that read it and its value when not given
PROTOCOL_OPTIONS: dict[str, tuple[tuple[Protocol, ...], object]] = {
    "runs": ((Protocol.PAPER, Protocol.OPEN_SET), RUNS),
    "seed": ((Protocol.PAPER, Protocol.OPEN_SET), SEED),
    "cross_condition": ((Protocol.PAPER, Protocol.OPEN_SET), False),
    "unknown_share": ((Protocol.OPEN_SET,), UNKNOWN_SHARE),
    "k_grid": ((Protocol.OPEN_SET,), K_GRID),
    "database": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
    "queries": ((Protocol.TRAVERSAL, Protocol.DATABASE), None),
}
#: the K of the table's Recall@K columns
TABLE_KS = (1, 5, 10)
#: the most cells one bench runs
MAX_CELLS = 1000
#: bytes per MiB, the table's unit of memory
MIB = 1 << 20


class BenchStages(Interface):
    """The pipeline's stages a bench runs with: the ``vpr_explorer.pipeline`` module is one."""

    def open_dataset(self, source: str | Path, layout: str = "auto", **options): ...

    def dataset_descriptors(self, dataset, descriptor: str, **options) -> np.ndarray: ...

    def imported_descriptors(self, dataset, path: Path, **options): ...

    def check_options(self, protocol: Protocol | str, dataset, options: ProtocolOptions | None = None) -> Protocol: ...

    def run_protocol(self, protocol: Protocol | str, dataset, places, descriptors: np.ndarray,
                     options: ProtocolOptions | None = None, **keywords) -> Evaluation: ...

    def evaluate_retrieval(self, dataset, descriptors: np.ndarray, options: ProtocolOptions | None = None,
                           **keywords) -> Evaluation: ...


def _unique(name: str, values: Sequence[str]) -> tuple[str, ...]:
    values = tuple(values)
    twice = sorted({v for v in values if values.count(v) > 1})
    if twice:
        raise VPRInputError(f"{name}: {', '.join(map(str, twice))} given twice; give each once")
    return values


@dataclass(frozen=True)
class BenchSpec:
    """The settings of one bench, checked when made (module doc).

    Attributes:
        datasets: dataset folders (or manifests), or ``"demo"``; each once.
        descriptors: extractor names (``descriptors.extractor_names``, or ``hub:DIR[:ENTRY]``), each
            run on every dataset.
        descriptor_options: ``(option, value)`` pairs given to every ``hub:DIR[:ENTRY]`` descriptor of
            ``descriptors`` (``descriptors.hub.OPTIONS``: ``hub_args``, ``input_size``, ``short_side``,
            ``normalisation``), as ``get_extractor(name, **options)`` takes them; the other
            descriptors get none.
        descriptor_files: ``(dataset, file)`` pairs: descriptors computed elsewhere for that
            dataset of ``datasets``, named by the file's stem (``pipeline.imported_descriptors``).
        protocols: the protocols every dataset runs, or None for each layout's default
            (``DEFAULT_PROTOCOL``).
        methods: method keys of the table's rows (``retrieval.METHODS_BY_KEY``), or None for every
            method of each cell's table.
        group, step, reading: places: frames (or metres, by ``geometry``) per place and between places.
        geometry: database/queries layouts: how group/step count (``PlaceGeometry``), or None for
            ``evaluate``'s default.
        layout: how every dataset is read (``layouts.Layout``; ``auto`` detects it).
        radius: position-tagged layouts: metres within which a database image is right, or None.
        runs, seed, cross_condition, unknown_share, k_grid, database, queries: the protocol
            options (``PROTOCOL_OPTIONS``), None where not given.
        tolerance: aligned traversals: frames of slack, or None (0).
        theta: a global θ of the user's, scored beside the automatic one, or None.
        dtype: descriptor precision, ``"float32"`` or ``"float16"``.
        cache_root: the descriptor cache folder, or None for ``settings.cache_root()``.

    Raises:
        VPRInputError: naming the setting and the fix.
    """

    datasets: tuple[str, ...]
    descriptors: tuple[str, ...] = ()
    descriptor_options: tuple[tuple[str, object], ...] = ()
    descriptor_files: tuple[tuple[str, Path], ...] = ()
    protocols: tuple[Protocol, ...] | None = None
    methods: tuple[str, ...] | None = None
    group: int | float = 3
    step: int | float = 10
    reading: Reading = Reading.STRIDE
    geometry: PlaceGeometry | None = None
    layout: Layout = Layout.AUTO
    radius: float | None = None
    runs: int | None = None
    seed: int | None = None
    cross_condition: bool | None = None
    unknown_share: float | None = None
    k_grid: tuple[float, ...] | None = None
    database: tuple[str, ...] | None = None
    queries: str | None = None
    tolerance: int | None = None
    theta: float | None = None
    dtype: str = "float32"
    cache_root: Path | None = None

    def __post_init__(self) -> None:
        from vpr_explorer.data.groundtruth import check_radius
        from vpr_explorer.descriptors import extractor_names, hub
        from vpr_explorer.descriptors.cache import check_dtype

        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen: set once, here)
        put("datasets", _unique("datasets", [str(d) for d in self.datasets]))
        if not self.datasets:
            raise VPRInputError("datasets: give at least one dataset folder (or 'demo')")
        put("descriptors", _unique("descriptors", self.descriptors))
        names = extractor_names()
        unknown = [d for d in self.descriptors if d not in names and not hub.is_hub_name(d)]
        if unknown:
            raise VPRInputError(f"descriptors: {', '.join(unknown)} unknown; choose among {', '.join(names)}, or "
                                "hub:DIR[:ENTRY] (a torch.hub repository folder), or bring a file of descriptors per "
                                "dataset")
        given = self.descriptor_options
        pairs = list(given.items() if isinstance(given, Mapping) else given)
        options = dict(pairs)
        if len(options) != len(pairs) or set(options) - set(hub.OPTIONS):
            raise VPRInputError(f"descriptor_options: {', '.join(str(k) for k, _ in pairs)}; give each of "
                                f"{', '.join(hub.OPTIONS)} at most once")
        if options and not any(hub.is_hub_name(d) for d in self.descriptors):
            raise VPRInputError(f"descriptor_options ({', '.join(options)}) apply to hub:DIR[:ENTRY] descriptors only, "
                                "and descriptors names none: drop them, or name a hub repository")
        put("descriptor_options", tuple(sorted(options.items())))
        put("descriptor_files", tuple((str(d), Path(f).expanduser()) for d, f in self.descriptor_files))
        for d, f in self.descriptor_files:
            if d not in self.datasets:
                raise VPRInputError(f"descriptor file {f}: dataset {d!r} is not one of the datasets")
        for d in self.datasets:
            _unique(f"descriptors of {d}", [*self.descriptors, *(f.stem for s, f in self.descriptor_files if s == d)])
        if not self.descriptors and not self.descriptor_files:
            raise VPRInputError("descriptors: name at least one extractor (e.g. pixels efficientnet-lite0), or give "
                                "a file of descriptors for a dataset")
        if self.protocols is not None:
            put("protocols", _unique("protocols", [_protocol(p) for p in self.protocols]))
            if not self.protocols:
                raise VPRInputError("protocols: give at least one, or none for each layout's default")
        if self.methods is not None:
            put("methods", _unique("methods", self.methods))
            bad = [m for m in self.methods if m not in METHODS_BY_KEY]
            if not self.methods or bad:
                raise VPRInputError(f"methods: {', '.join(bad) or 'none given'}; choose among "
                                    f"{', '.join(METHODS_BY_KEY)}")
            if "global-user" in self.methods and self.theta is None:
                raise VPRInputError("methods: global-user is the θ you give: give --theta too, or drop global-user")
        put("reading", _choice(Reading, self.reading, "reading"))
        try:  # frames or metres, as each dataset reads them: a value neither can be is refused here
            PlaceSpec(self.group, self.step, self.reading)
        except VPRInputError:
            MetricPlaceSpec(self.group, self.step, self.reading)
        if self.geometry is not None:
            put("geometry", _choice(PlaceGeometry, self.geometry, "geometry"))
        put("layout", _choice(Layout, self.layout, "layout"))
        if self.radius is not None:
            put("radius", check_radius(self.radius, "radius"))
        put("dtype", check_dtype(self.dtype, "dtype"))
        if self.database is not None:
            put("database", (self.database,) if isinstance(self.database, str) else tuple(self.database))
        if self.k_grid is not None:
            put("k_grid", tuple(self.k_grid))
        # every value checked once, as ProtocolOptions checks it
        ProtocolOptions(**{name: value for name, value in self.given().items() if name != "theta"},
                        user_theta=self.theta)
        if self.protocols is not None:
            self.check_read(self.protocols)

    def given(self) -> dict[str, object]:
        """The protocol options given (``PROTOCOL_OPTIONS``' names), the tolerance and θ where given."""
        names = (*PROTOCOL_OPTIONS, "tolerance", "theta")
        return {name: getattr(self, name) for name in names if getattr(self, name) is not None}

    def check_read(self, protocols: Sequence[Protocol]) -> None:
        """Refuse a protocol option that none of ``protocols`` reads, naming it and the protocols that do."""
        for name, (readers, _) in PROTOCOL_OPTIONS.items():
            if getattr(self, name) is not None and not set(readers) & set(protocols):
                raise VPRInputError(f"{option(name)} applies to the {' and '.join(p.value for p in readers)} protocol"
                                    f"{'s' if len(readers) > 1 else ''} only, and the bench runs "
                                    f"{', '.join(p.value for p in protocols)}: drop it, or run one of those")

    def options(self, protocol: Protocol) -> ProtocolOptions:
        """The ``ProtocolOptions`` of an aligned-traversals cell: the options ``protocol`` reads, the rest defaults."""
        fields = {name: (default if getattr(self, name) is None or protocol not in readers else getattr(self, name))
                  for name, (readers, default) in PROTOCOL_OPTIONS.items()}
        return ProtocolOptions(**fields, tolerance=self.tolerance or 0, user_theta=self.theta, pr=True)

    def extractor_options(self, descriptor: str) -> dict[str, object]:
        """``get_extractor``'s options for ``descriptor``: ``descriptor_options`` for a ``hub:`` name, else none."""
        from vpr_explorer.descriptors.hub import is_hub_name

        return dict(self.descriptor_options) if is_hub_name(descriptor) else {}

    def files(self, dataset: str) -> tuple[Path, ...]:
        return tuple(f for d, f in self.descriptor_files if d == dataset)

    def to_dict(self) -> dict:
        """Every setting, those not given at the value the runs used (``None``: the layout's or the command's)."""
        from vpr_explorer.settings import cache_root

        return {
            "datasets": list(self.datasets), "descriptors": list(self.descriptors),
            "descriptor_options": {k: _plain(v) for k, v in self.descriptor_options} or None,
            "descriptor_files": [{"dataset": d, "file": str(f)} for d, f in self.descriptor_files],
            "protocols": None if self.protocols is None else [p.value for p in self.protocols],
            "methods": None if self.methods is None else list(self.methods),
            "group": self.group, "step": self.step, "reading": self.reading.value,
            "geometry": None if self.geometry is None else self.geometry.value, "layout": self.layout.value,
            "radius": self.radius,
            **{name: _plain(default if getattr(self, name) is None else getattr(self, name))
               for name, (_, default) in PROTOCOL_OPTIONS.items()},
            "tolerance": self.tolerance or 0, "theta": self.theta, "pr": True, "dtype": self.dtype,
            "cache_root": str(cache_root() if self.cache_root is None else self.cache_root),
            "given": sorted(self.given()),
        }


def option(name: str) -> str:
    """The command-line option of a ``BenchSpec`` field: ``unknown_share`` -> ``--unknown-share``."""
    return "--" + name.replace("_", "-")


def _plain(value):
    return list(value) if isinstance(value, tuple) else value


def _choice(kind, value, name: str):
    """``kind(value)`` for a ``StrEnum`` ``kind``, or a ``VPRInputError`` naming ``name`` and the choices."""
    try:
        return kind(value)
    except ValueError:
        raise VPRInputError(f"{name} {value!r}: choose among {', '.join(x.value for x in kind)}") from None


def _protocol(value: Protocol | str) -> Protocol:
    return _choice(Protocol, value, "protocol")


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class DatasetRun:
    """One dataset of the bench as read: its name and layout, or why it could not be read."""

    source: str
    name: str
    layout: str | None = None
    n_images: int | None = None
    description: str = ""
    notes: tuple[str, ...] = ()
    error: str | None = None

    def to_dict(self) -> dict:
        return {"source": self.source, "name": self.name, "layout": self.layout, "n_images": self.n_images,
                "description": self.description, "notes": list(self.notes), "error": self.error}


@dataclass(frozen=True)
class DescriptorRun:
    """One dataset × descriptor's descriptors: where they came from and what they cost (module doc).

    A dataset whose cells all fail before any descriptor is needed has none. ``error`` says
    why the step failed (its numbers are then ``None``).
    """

    dataset: str
    descriptor: str
    source: dict[str, str] = field(default_factory=dict)
    n_images: int | None = None
    dim: int | None = None
    dtype: str | None = None
    seconds: float | None = None
    python_peak: int | None = None
    rss_growth: int | None = None
    cached_images: int | None = None
    error: str | None = None

    def to_dict(self) -> dict:
        return {"dataset": self.dataset, "descriptor": self.descriptor, **self.source, "n_images": self.n_images,
                "dim": self.dim, "dtype": self.dtype, "seconds": self.seconds, "python_peak_bytes": self.python_peak,
                "rss_growth_bytes": self.rss_growth, "cached_images": self.cached_images, "error": self.error}


@dataclass(frozen=True, eq=False)
class BenchCell:
    """One dataset × descriptor × protocol: its evaluation, or why it has none.

    ``protocol`` is None only for a dataset that could not be read when no protocols were
    named (its layout's default is unknown). ``seconds``: the protocol run's wall clock here.
    """

    dataset: str
    source: str
    descriptor: str
    protocol: Protocol | None
    evaluation: Evaluation | None = field(default=None, repr=False)
    error: str | None = None
    seconds: float = 0.0

    @property
    def failed(self) -> bool:
        return self.error is not None

    def to_dict(self) -> dict:
        """The cell's settings and numbers: ``Evaluation.to_dict`` without its curves (the report draws them),
        with ``recall_over_every_query`` for a database-queries cell, as ``evaluate --json`` writes them."""
        ev = None
        if self.evaluation is not None:
            ev = {k: v for k, v in self.evaluation.to_dict().items() if k != "pr_curves"}
            every = recall_over_every_query(self.evaluation)
            if every is not None:
                ev["recall_over_every_query"] = {str(k): v for k, v in every.items()}
        return {"dataset": self.dataset, "source": self.source, "descriptor": self.descriptor,
                "protocol": None if self.protocol is None else self.protocol.value, "error": self.error,
                "seconds": self.seconds, "evaluation": ev}


#: the table's columns: name -> what it holds (rates in [0, 1]; "" or None where there is nothing)
COLUMNS = {
    "dataset": "the dataset's name", "source": "the dataset as given", "descriptor": "the descriptor's name",
    "protocol": "the protocol", "method": "the method's key", "label": "the method's label",
    "status": "ok, failed (the cell has no numbers: see message) or missing (not in this cell's table)",
    "message": "why the cell failed or the method is missing",
    **{f"r{k}{s}": f"Recall@{k}, {w} over runs" for k in TABLE_KS for s, w in (("", "mean"), ("_std", "std"))},
    "auc": "area under the method's precision–recall curve (pooled over runs)",
    "r_at_100p": "recall at 100% precision", "max_f1": "max F1 on the method's curve",
    "rejection": "unknown-place rejection (mean over runs), where the protocol has unknown queries",
    "accepted": "share of queries accepted (mean)", "precision": "precision of accepted matches (mean)",
    "extract_seconds": "seconds to extract or read the dataset × descriptor's descriptors",
    "python_peak_mib": "peak Python-tracked memory of that step above its start (tracemalloc), MiB",
    "rss_growth_mib": "rise of the process's resident high-water mark during that step (ru_maxrss), MiB",
    "cached_images": "images of that step already in the descriptor cache",
    "protocol_seconds": "seconds of the cell's protocol run",
}


@dataclass(frozen=True, eq=False)
class BenchResult:
    """What :func:`run_bench` returns: the spec, each dataset and descriptors step, every cell in run order."""

    spec: BenchSpec
    datasets: tuple[DatasetRun, ...]
    descriptors: tuple[DescriptorRun, ...]
    cells: tuple[BenchCell, ...]
    seconds: float = 0.0

    @property
    def failed(self) -> tuple[BenchCell, ...]:
        return tuple(c for c in self.cells if c.failed)

    def descriptor_run(self, dataset: str, descriptor: str) -> DescriptorRun | None:
        return next((d for d in self.descriptors if d.dataset == dataset and d.descriptor == descriptor), None)

    def rows(self) -> list[dict]:
        """The table: one dict per cell × method (``COLUMNS``), a failed cell one row with its message."""
        rows = []
        for cell in self.cells:
            run = self.descriptor_run(cell.source, cell.descriptor)
            base = {c: None for c in COLUMNS} | {
                "dataset": cell.dataset, "source": cell.source, "descriptor": cell.descriptor,
                "protocol": "" if cell.protocol is None else cell.protocol.value, "method": "", "label": "",
                "status": "ok", "message": "", "protocol_seconds": cell.seconds, **_cost(run)}
            if cell.evaluation is None:
                rows.append(base | {"status": "failed", "message": cell.error})
                continue
            ev = cell.evaluation
            keys = self.spec.methods if self.spec.methods is not None else [r.key for r in ev.rows]
            by_key = {r.key: r for r in ev.rows}
            pr = {p.key: p for p in ev.pr}
            for key in keys:
                if key not in by_key:
                    rows.append(base | {"method": key, "label": METHODS_BY_KEY[key].label, "status": "missing",
                                        "message": f"{key} is not in the {ev.protocol.value} protocol's table here"})
                    continue
                rows.append(base | _numbers(by_key[key], pr.get(key)))
        return rows

    def table(self) -> str:
        """The table as text: rates in %, AUC to three places, seconds and MiB to one; failed cells' messages below."""
        header = ["dataset", "descriptor", "protocol", "method", *(f"R@{k}" for k in TABLE_KS), "AUC", "R@100P",
                  "max F1", "rejected", "extract s", "peak MiB", "RSS+ MiB"]
        lines = []
        failed = []
        for r in self.rows():
            if r["status"] == "failed":
                failed.append(r)
            method = {"failed": "failed (below)", "missing": f"{r['label']} (missing)"}.get(r["status"], r["label"])
            lines.append([r["dataset"], r["descriptor"], r["protocol"] or "—", method,
                          *(_pct(r[f"r{k}"]) for k in TABLE_KS), _fmt(r["auc"], "{:.3f}"), _pct(r["r_at_100p"]),
                          _pct(r["max_f1"]), _pct(r["rejection"]), _fmt(r["extract_seconds"], "{:.1f}"),
                          _fmt(r["python_peak_mib"], "{:.1f}"), _fmt(r["rss_growth_mib"], "{:.1f}")])
        widths = [max(len(h), *(len(x[i]) for x in lines)) if lines else len(h) for i, h in enumerate(header)]

        def line(cells: list[str]) -> str:
            return "  ".join(c.ljust(w) if i < 4 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

        out = [line(header), "  ".join("-" * w for w in widths), *map(line, lines)]
        if failed:
            out.append("")
            out += [f"failed: {r['dataset']} · {r['descriptor']} · {r['protocol'] or '—'}: {r['message']}"
                    for r in failed]
        return "\n".join(out)

    def to_csv(self) -> str:
        """The table, one row per cell × method, with every bench setting in a column of its own."""
        settings = {k: (" ".join(map(str, v)) if isinstance(v, list) else v) for k, v in self.spec.to_dict().items()
                    if k not in ("datasets", "descriptors", "descriptor_files", "protocols", "methods")}
        columns = [*COLUMNS, *(f"setting_{k}" for k in settings)]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        w.writeheader()
        for row in self.rows():
            w.writerow({k: ("" if v is None else repr(v) if isinstance(v, float) else v) for k, v in row.items()}
                       | {f"setting_{k}": "" if v is None else v for k, v in settings.items()})
        return buf.getvalue()

    def to_dict(self) -> dict:
        """JSON-ready: the settings, the datasets, the descriptors steps, every cell's evaluation and the table."""
        return strict({
            "settings": self.spec.to_dict(), "seconds": self.seconds, "failed": len(self.failed),
            "columns": COLUMNS, "memory": {"python_peak": MEMORY_NOTES[0], "rss_growth": MEMORY_NOTES[1]},
            "datasets": [d.to_dict() for d in self.datasets],
            "descriptors": [d.to_dict() for d in self.descriptors],
            "cells": [c.to_dict() for c in self.cells], "rows": self.rows(),
        })

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False)


#: what the two memory figures measure (``DescriptorRun``)
MEMORY_NOTES = (
    "tracemalloc: peak of Python-tracked allocations (numpy arrays included; not torch's or PIL's own) during the "
    "descriptors step, above those live at its start",
    "getrusage ru_maxrss: how far the process's resident high-water mark rose during the descriptors step "
    "(everything, but 0 when the step stayed under the process's earlier peak)",
)


def _cost(run: DescriptorRun | None) -> dict:
    """The descriptors step's columns of a row."""
    if run is None:
        return {}
    mib = lambda b: None if b is None else b / MIB  # noqa: E731
    return {"extract_seconds": run.seconds, "python_peak_mib": mib(run.python_peak),
            "rss_growth_mib": mib(run.rss_growth), "cached_images": run.cached_images}


def _mean(stat) -> float | None:
    return None if stat is None or not math.isfinite(stat[0]) else float(stat[0])


def _std(stat) -> float | None:
    return None if stat is None or not math.isfinite(stat[1]) else float(stat[1])


def _finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _numbers(row, pr) -> dict:
    """A method's columns: its ``MethodRow`` and its precision–recall row (``None`` where the run has none)."""
    numbers = {"method": row.key, "label": row.label, "accepted": _mean(row.accepted),
               "precision": _mean(row.precision), "rejection": _mean(row.unknown_rejection)}
    for k in TABLE_KS:
        stat = row.recall.get(k)
        numbers[f"r{k}"], numbers[f"r{k}_std"] = _mean(stat), _std(stat)
    if pr is not None:
        numbers |= {"auc": _finite(pr.auc), "r_at_100p": _finite(pr.r_at_100p), "max_f1": _finite(pr.max_f1)}
    return numbers


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def _fmt(x: float | None, fmt: str) -> str:
    return "—" if x is None else fmt.format(x)


# --------------------------------------------------------------------------- the runs


@dataclass(frozen=True, eq=False)
class _Opened:
    """A dataset read, with each protocol's way to run (places, options) or why it cannot."""

    run: DatasetRun
    dataset: object | None = None
    setups: dict = field(default_factory=dict)  # Protocol | None -> _Setup


@dataclass(frozen=True, eq=False)
class _Setup:
    error: str | None = None
    places: object | None = None  # aligned: Places
    options: ProtocolOptions | None = None
    spec: PlaceSpec | None = None  # database/queries: its places
    metric: MetricPlaceSpec | None = None


def _open(spec: BenchSpec, stages: BenchStages, source: str) -> _Opened:
    """Read one dataset and check every protocol of it against its layout, before any descriptor is computed."""
    try:
        dataset = stages.open_dataset(source, spec.layout.value, radius=spec.radius, database=spec.database,
                                      queries=spec.queries)
    except VPRInputError as exc:
        protocols = spec.protocols or (None,)
        return _Opened(DatasetRun(source, source, error=str(exc)), setups={p: _Setup(str(exc)) for p in protocols})
    retrieval = isinstance(dataset, RetrievalDataset)
    layout = dataset.layout.value if retrieval else ("prepared" if dataset.prepared_places is not None
                                                     else Layout.TRAVERSALS.value)
    described = (dataset.describe() if retrieval else f"{dataset.n_traversals} traversals "
                 f"({', '.join(dataset.traversals)}) × {dataset.n_frames:,} frames")
    run = DatasetRun(source, dataset.name, layout, dataset.n_images, described, tuple(dataset.notes))
    protocols = spec.protocols or (DEFAULT_PROTOCOL[retrieval],)
    setup = _retrieval_setup if retrieval else _aligned_setup
    try:
        setups = setup(spec, stages, dataset, protocols)
    except VPRInputError as exc:
        setups = {p: _Setup(str(exc)) for p in protocols}
    return _Opened(run, dataset, setups)


def _aligned_setup(spec: BenchSpec, stages: BenchStages, dataset, protocols) -> dict:
    """Each protocol's places and options on aligned traversals (``evaluate``'s path), or why it does not apply."""
    if spec.geometry is not None:
        raise VPRInputError(f"--geometry applies to database/queries layouts; {dataset.name} is read as traversal "
                            "folders, whose places are group/step over frames")
    places = make_places(dataset, PlaceSpec(spec.group, spec.step, spec.reading))
    setups = {}
    for protocol in protocols:
        if protocol not in ALIGNED_PROTOCOLS:
            setups[protocol] = _Setup(f"protocol {protocol.value} needs a database/queries layout; {dataset.name} "
                                      f"holds aligned traversals: use {', '.join(p.value for p in ALIGNED_PROTOCOLS)}")
            continue
        options = spec.options(protocol)
        try:
            stages.check_options(protocol, dataset, options)
        except VPRInputError as exc:
            setups[protocol] = _Setup(str(exc))
            continue
        setups[protocol] = _Setup(places=places, options=options)
    return setups


def _retrieval_setup(spec: BenchSpec, stages: BenchStages, dataset: RetrievalDataset, protocols) -> dict:
    """The database-queries protocol's places on a database/queries layout (``evaluate``'s path)."""
    from vpr_explorer.method.places import retrieval_places

    if spec.radius is not None and not radius_applies(dataset):
        raise VPRInputError(f"--radius applies to position-tagged layouts; {dataset.name} is {dataset.layout.value}, "
                            f"which takes its ground truth from {dataset.ground_truth.description}: drop --radius")
    if spec.tolerance:
        raise VPRInputError("--tolerance counts frames of aligned traversals; a database/queries layout says which "
                            "images are right by its ground truth (position-tagged: --radius)")
    geometry = spec.geometry
    if geometry is None:
        geometry = (PlaceGeometry.FRAMES if dataset.database_xy is None
                    else PlaceGeometry.ROUTE if dataset.ordered else PlaceGeometry.LATTICE)
    if geometry is PlaceGeometry.FRAMES:
        place_spec, metric = PlaceSpec(spec.group, spec.step, spec.reading), None
    else:
        place_spec, metric = None, MetricPlaceSpec(spec.group, spec.step, spec.reading, geometry)
    retrieval_places(dataset, place_spec, metric)  # places that cannot be made fail here, before extraction
    options = ProtocolOptions(user_theta=spec.theta, pr=True)
    return {p: (_Setup(options=options, spec=place_spec, metric=metric) if p is Protocol.DATABASE else
                _Setup(f"protocol {p.value}: {dataset.name} is a {dataset.layout.value} layout, whose queries are "
                       f"given: use {Protocol.DATABASE.value} (the default for it)"))
            for p in protocols}


def _max_rss() -> int | None:
    """The process's resident high-water mark in bytes (``ru_maxrss``: KiB on Linux, bytes on macOS), or None."""
    try:
        import resource
    except ImportError:  # pragma: no cover (Windows)
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


@contextmanager
def measured() -> Iterator[dict]:
    """Measure the block: ``seconds``, ``python_peak`` and ``rss_growth`` (module doc) in the dict it yields.

    tracemalloc is started for the block and stopped after it, unless it was tracing
    already (then its peak is reset, and it keeps tracing).
    """
    tracing = tracemalloc.is_tracing()
    if tracing:
        tracemalloc.reset_peak()
    else:
        tracemalloc.start()
    live = tracemalloc.get_traced_memory()[0]
    rss = _max_rss()
    box: dict = {}
    start = time.perf_counter()
    try:
        yield box
    finally:
        box["seconds"] = time.perf_counter() - start
        box["python_peak"] = max(0, tracemalloc.get_traced_memory()[1] - live)
        if not tracing:
            tracemalloc.stop()
        after = _max_rss()
        box["rss_growth"] = None if rss is None or after is None else max(0, after - rss)


def _descriptors(spec: BenchSpec, stages: BenchStages, opened: _Opened, name: str, file: Path | None,
                 progress: Callable | None) -> tuple[np.ndarray | None, dict[str, str], DescriptorRun]:
    """One dataset × descriptor's descriptors, measured: ``(descriptors or None, their source settings, the run)``.

    The source settings: a file's path and sha256 (``ImportedDescriptors.settings``), or a hub
    descriptor's options (``descriptors.hub.hub_settings``; nothing for the other extractors).
    """
    dataset = opened.dataset
    first: list[int] = []

    def counted(done: int, total: int, *message) -> None:
        if not first:
            first.append(done)  # extract_descriptors' first call counts the cache hits
        if progress is not None:
            progress(done, total, *message)

    source = {} if file is not None else hub_settings(spec.extractor_options(name))
    try:
        with measured() as cost:
            if file is not None:
                imp = stages.imported_descriptors(dataset, file, dtype=spec.dtype)
                desc, source = imp.descriptors, imp.settings()
            else:
                desc = stages.dataset_descriptors(dataset, name, cache_root=spec.cache_root, progress=counted,
                                                  dtype=spec.dtype, options=spec.extractor_options(name))
    except VPRInputError as exc:
        return None, source, DescriptorRun(opened.run.source, name, error=str(exc))
    run = DescriptorRun(opened.run.source, name, source, int(desc.shape[0]), int(desc.shape[1]), str(desc.dtype),
                        cost["seconds"], cost["python_peak"], cost["rss_growth"],
                        None if file is not None else (first[0] if first else None))
    return desc, source, run


def bench_cells(spec: BenchSpec, protocols_of: dict[str, Sequence[Protocol | None]]) -> int:
    """How many cells ``spec`` makes, given each dataset's protocols; refused above ``MAX_CELLS``."""
    n = sum(len(protocols_of[d]) * (len(spec.descriptors) + len(spec.files(d))) for d in spec.datasets)
    if n > MAX_CELLS:
        raise VPRInputError(f"{n:,} cells (datasets × descriptors × protocols): at most {MAX_CELLS:,}; run fewer "
                            "at once")
    return n


def run_bench(spec: BenchSpec, stages: BenchStages, *,
              progress_for: Callable[[str], Callable] | None = None) -> BenchResult:
    """Run every cell of ``spec`` (module doc): each dataset read once, each descriptors step once.

    Args:
        spec: the bench.
        stages: the pipeline's stages (``vpr_explorer.pipeline``).
        progress_for: ``progress_for(label)`` -> a progress callback ``(done, total, *message)``
            for one step: a descriptors step (label ``"DATASET · DESCRIPTOR"``) or a cell's protocol
            run (``"DATASET · DESCRIPTOR · PROTOCOL"``); each step gets its own.

    Returns:
        The datasets, descriptors steps and cells, in run order (datasets, then descriptors,
        then protocols, each in ``spec``'s order).

    Raises:
        VPRInputError: the cache folder cannot be written, a protocol option no cell's protocol
            reads, or more than ``MAX_CELLS`` cells; before any descriptor is computed.
            Everything else a cell meets is its ``error``.
    """
    from vpr_explorer.settings import check_cache_root

    start = time.perf_counter()
    if spec.descriptors:
        check_cache_root(spec.cache_root)
    opened = [_open(spec, stages, source) for source in spec.datasets]
    if spec.protocols is None and any(o.dataset is not None for o in opened):
        spec.check_read(sorted({p for o in opened if o.dataset is not None for p in o.setups}, key=list(Protocol).index))
    bench_cells(spec, {o.run.source: tuple(o.setups) for o in opened})
    step = (lambda label: None) if progress_for is None else progress_for
    runs: list[DescriptorRun] = []
    cells: list[BenchCell] = []
    for o in opened:
        named = [(d, None) for d in spec.descriptors] + [(f.stem, f) for f in spec.files(o.run.source)]
        for name, file in named:
            cell = lambda protocol, **kw: BenchCell(o.run.name, o.run.source, name, protocol, **kw)  # noqa: E731
            runnable = [p for p, s in o.setups.items() if s.error is None]
            if not runnable:  # no descriptors step: nothing could use it
                cells += [cell(p, error=s.error) for p, s in o.setups.items()]
                continue
            desc, source, run = _descriptors(spec, stages, o, name, file, step(f"{o.run.name} · {name}"))
            runs.append(run)
            shared = None
            if desc is not None and not isinstance(o.dataset, RetrievalDataset) and len(desc) <= SHARED_LIMIT:
                shared = SharedScores(desc)
            for protocol, setup in o.setups.items():
                if setup.error is not None or desc is None:
                    cells.append(cell(protocol, error=setup.error or run.error))
                    continue
                t0 = time.perf_counter()
                try:
                    ev = _evaluate(spec, stages, o.dataset, desc, name, source, protocol, setup,
                                   step(f"{o.run.name} · {name} · {protocol.value}"), shared)
                except VPRInputError as exc:
                    cells.append(cell(protocol, error=str(exc), seconds=time.perf_counter() - t0))
                    continue
                cells.append(cell(protocol, evaluation=ev, seconds=time.perf_counter() - t0))
    return BenchResult(spec, tuple(o.run for o in opened), tuple(runs), tuple(cells), time.perf_counter() - start)


def _evaluate(spec: BenchSpec, stages: BenchStages, dataset, descriptors: np.ndarray, name: str,
              source: dict[str, str], protocol: Protocol, setup: _Setup, progress: Progress | None,
              shared: SharedScores | None) -> Evaluation:
    """One cell's run, with the settings ``evaluate`` records (its descriptor, file or hub options, and dtype)."""
    if isinstance(dataset, RetrievalDataset):
        return stages.evaluate_retrieval(dataset, descriptors, setup.options, spec=setup.spec, metric=setup.metric,
                                         settings={"descriptor": name, **source, "dtype": spec.dtype},
                                         progress=progress)
    return stages.run_protocol(protocol, dataset, setup.places, descriptors, setup.options, progress=progress,
                               settings={"descriptor": name, **source, "dtype": str(descriptors.dtype)},
                               shared=shared)
