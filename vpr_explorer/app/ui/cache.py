"""Every Streamlit cache of the app, in one place, chained like the data flow.

dataset (listing, in its layout) -> descriptors (extraction, on-disk cache; or a descriptor
file: one the app was started with, or one typed on the Dataset page) -> the dataset value
(``value``: aligned traversals become a database/queries dataset for the chosen query
traversal) -> fitted (places, database thresholds) -> query decision / next rejected query,
and -> overview (the queries decided, sampled on big datasets) / evaluation. Pages that show
one place or one query only need ``fitted``: they never compute query × database pairs
beyond their own row. Places come from ``numbers.RetrievalPlaces`` (the layout's
own ids, frames, or metres along a route or over a lattice).

Keys: Streamlit samples large arrays when it hashes them, so functions never hash the
descriptors; they take them as an underscore argument (unhashed) beside ``data.key``,
which holds the descriptors' content ``fingerprint()``. Models and big matrices go in
``st.cache_resource`` (returned as is, never mutated), small results in
``st.cache_data``. Work that reports progress (extraction, evaluation protocols) goes
through ``_memo`` instead: a cached function replays the ``st.*`` calls made inside it,
which must not happen to a progress bar.

Every dataset and typed descriptor file is looked up under the app's data root
(``app.under_data_root``) before anything of it is read: ``dataset``, ``layout_of`` and
``check_descriptor_file`` refuse a path outside it (the files the app was started with,
``descriptor_files``, are the operator's and read where they are). A ``hub:DIR[:ENTRY]``
descriptor name (whose ``hubconf.py`` would run in the server) is refused by ``load`` whatever
names it: the app runs a torch.hub model only by the name the operator's models settings file
gives it (``descriptors.custom``).

When the cache folder cannot be written (``disk_cache_problem``), the explorer still
runs: descriptors are kept in memory only and the demo route is drawn into the
temporary folder; the Dataset page says so.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import streamlit as st
from PIL import Image

from vpr_explorer import settings
from vpr_explorer.app import data_root, descriptor_files, under_data_root
from vpr_explorer.method.retrieval import QueryDecision
from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.traversals import Dataset, load_dataset
from vpr_explorer.descriptors import extract_descriptors, fingerprint, get_extractor
from vpr_explorer.descriptors.base import open_image
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import Evaluation
from vpr_explorer.data.layouts import RETRIEVAL_LAYOUTS, Layout, RetrievalDataset, detect_layout
from vpr_explorer.pipeline import (
    DEMO,
    dataset_descriptors,
    evaluate_retrieval,
    imported_descriptors,
    open_dataset,
    resolve_dataset,
    run_protocol,
)
from vpr_explorer.method.places import MetricPlaceSpec, PlaceGeometry, PlaceSpec, retrieval_places
from vpr_explorer.method.stats import fit_device
from vpr_explorer.protocols.acceptance import AcceptanceReport, BenchOptions, acceptance_report
from vpr_explorer.protocols.shared_scores import SHARED_LIMIT, SharedScores
from vpr_explorer.views import numbers as views
from vpr_explorer.method import stats
from vpr_explorer.views.numbers import RetrievalFitted, RetrievalOverview, RetrievalPlaces

from vpr_explorer.app.ui.feedback import progress_reporter

MEMO_ENTRIES = 8
# Seconds a cache-folder check is trusted: it writes a probe file, so not on every rerun.
CACHE_CHECK_TTL = 10


@dataclass(frozen=True, eq=False)
class Loaded:
    """A dataset with its descriptors: what every page after the Dataset page starts from.

    Attributes:
        dataset: the dataset: aligned traversals (``Dataset``) or database and queries
            (``layouts.RetrievalDataset``).
        descriptor: extractor name, or a descriptor file's stem.
        descriptors: ``(n_images, D)`` L2-normalised, read-only.
        key: content key (dataset files + descriptor fingerprint) for the caches below.
        notes: what reading a descriptor file decided (format, name matches), one sentence each.
    """

    dataset: Dataset | RetrievalDataset
    descriptor: str
    descriptors: np.ndarray
    key: str
    notes: tuple[str, ...] = ()


# --------------------------------------------------------------------------- memo with progress


class _Memo:
    """A small thread-safe LRU shared by all sessions, for results computed with a progress bar."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.items: OrderedDict[tuple, object] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: tuple) -> object | None:
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
        return None

    def put(self, key: tuple, value: object) -> None:
        with self.lock:
            self.items[key] = value
            self.items.move_to_end(key)
            while len(self.items) > self.size:
                self.items.popitem(last=False)


@st.cache_resource(show_spinner=False)
def _memo() -> _Memo:
    return _Memo(MEMO_ENTRIES)


@dataclass(frozen=True)
class _Failed:
    """A remembered ``VPRInputError``: a rerun shows it at once instead of redoing the work up to it."""

    message: str


def _memoised(key: tuple, label: str, compute: Callable[[Callable[..., None]], object]) -> object:
    hit = _memo().get(key)
    if isinstance(hit, _Failed):
        raise VPRInputError(hit.message)
    if hit is not None:
        return hit
    progress, clear = progress_reporter(label)
    try:
        value = compute(progress)
    except VPRInputError as exc:
        # Keys hold the files' sizes and mtimes, so fixing the file makes a new key.
        _memo().put(key, _Failed(str(exc)))
        raise
    finally:
        clear()
    _memo().put(key, value)
    return value


# --------------------------------------------------------------------------- dataset and descriptors


#: Files beside the images that a layout reads (ground truth, positions, manifests): edited in
#: place they change no folder's mtime, so they are stamped themselves.
_SIDE_FILES = ("ground_truth_new.npy", "manifest.csv", "positions.csv")


def _folder_stamp(source: str) -> str:
    """Changes when a dataset's listing may have changed (the mtimes of its folder, sub-folders and side files)."""
    if source == DEMO:
        return f"demo@{settings.cache_root()}:{disk_cache_problem() is None}"
    root = Path(source).expanduser()
    try:
        parts = [f"{root.resolve()}:{root.stat().st_mtime_ns}:{root.stat().st_size}"]
        if root.is_dir():
            subs = [p for p in sorted(root.iterdir()) if p.is_dir()]
            parts += [f"{p.name}:{p.stat().st_mtime_ns}" for p in subs]
            for folder in (root, *subs, root / "images" / "test"):
                parts += [f"{f}:{f.stat().st_mtime_ns}:{f.stat().st_size}" for f in (folder / n for n in _SIDE_FILES)
                          if f.is_file()]
    except OSError:
        return "missing"
    return "|".join(parts)


@st.cache_data(show_spinner=False, ttl=CACHE_CHECK_TTL)
def _cache_problem(root: str) -> str | None:
    try:
        settings.check_cache_root(root)
    except VPRInputError as exc:
        return str(exc)
    return None


def disk_cache_problem() -> str | None:
    """Why nothing can be cached on disk (the cache folder cannot be written), or ``None`` when it can."""
    return _cache_problem(str(settings.cache_root()))


def _demo_in_temporary_folder() -> Dataset:
    """The demo route drawn under the temporary folder, for when the cache folder cannot hold it."""
    from vpr_explorer.data import demo

    uid = os.getuid() if hasattr(os, "getuid") else "user"
    root = Path(tempfile.gettempdir()) / f"vpr_explorer-{uid}" / demo.demo_root().relative_to(settings.cache_root())
    if not demo.route_is_complete(root):
        try:
            demo.write_demo_route(root)
        except OSError:
            if not demo.route_is_complete(root):  # another session may have installed it meanwhile
                raise
    return dataclasses.replace(load_dataset(root, list(demo.DEMO_TRAVERSALS)), name=DEMO)


def layout_of(source: str, layout: str = Layout.AUTO.value) -> Layout:
    """The layout ``source`` is read in: ``layout`` when named, else detected (``layouts.detect_layout``)."""
    try:
        named = Layout(layout)
    except ValueError:
        raise VPRInputError(f"layout {layout!r}: choose one of {', '.join(x.value for x in Layout)}") from None
    if named is not Layout.AUTO:
        return named
    if source == DEMO:
        return Layout.TRAVERSALS
    path = under_data_root(source, what="dataset")
    if not path.exists():
        raise VPRInputError(f"{path}: the dataset folder does not exist; check the path")
    return detect_layout(path)


@st.cache_resource(show_spinner="Reading the dataset folder…", max_entries=8)
def _dataset(source: str, layout: str, radius: float | None, stamp: str) -> Dataset | RetrievalDataset:
    if source == DEMO and layout in (Layout.AUTO.value, Layout.TRAVERSALS.value):
        if disk_cache_problem() is not None:
            return _demo_in_temporary_folder()
        return resolve_dataset(source)
    if source == DEMO:
        return open_dataset(source, layout)  # refuses, naming the layout
    positions = layout_of(source, layout) in RETRIEVAL_LAYOUTS
    return open_dataset(source, layout, radius=radius if positions else None, within=data_root())


def dataset(source: str, layout: str = Layout.AUTO.value, radius: float | None = None) -> Dataset | RetrievalDataset:
    """The dataset at ``source`` (a folder, a manifest ``.csv`` or ``"demo"``) read in ``layout``.

    ``radius`` (metres; default the field's 25) applies to position-tagged layouts and is
    ignored for the others. Raises ``VPRInputError`` for bad folders and files, and
    ``app.OutsideDataRoot`` for a path outside the app's data root (nothing of it read).
    """
    if source != DEMO:
        source = str(under_data_root(source, what="dataset"))
    return _dataset(source, layout, None if radius is None else float(radius), _folder_stamp(source))


def _files_key(ds: Dataset | RetrievalDataset) -> str:
    """A digest of every image's path, size and mtime: descriptors are recomputed when one changes."""
    h = hashlib.sha256()
    for p in ds.image_paths:
        try:
            s = p.stat()
        except OSError as exc:
            raise VPRInputError(f"{p}: cannot read the image file ({exc}); check the dataset folder") from exc
        h.update(f"{p}|{s.st_size}|{s.st_mtime_ns}\n".encode())
    return h.hexdigest()


_NAMES_KEYS: dict[int, tuple[object, str]] = {}


def _names_key(ds: Dataset | RetrievalDataset) -> str:
    """A digest of every image's path only, once per dataset object: the images' key when the
    descriptors come from a file (its own size and mtime are in the key; an edited image changes
    no number then, only what the page shows), so a 1,000,000-image database is not stat'ed on
    every script run (about 3 s, ``benchmarks/bench_million.py``)."""
    hit = _NAMES_KEYS.get(id(ds))
    if hit is not None and hit[0] is ds:
        return hit[1]
    digest = hashlib.sha256("\n".join(map(str, ds.image_paths)).encode()).hexdigest()
    if len(_NAMES_KEYS) >= 8:
        _NAMES_KEYS.clear()
    _NAMES_KEYS[id(ds)] = (ds, digest)
    return digest


def _images_key(ds: Dataset | RetrievalDataset, path: Path | None) -> str:
    """``_files_key`` for descriptors computed from the images, ``_names_key`` for a descriptor file (for a
    run folder, with its files' sizes and mtimes: ``vme_run.run_stamp``)."""
    if (path is not None and path.is_dir() and isinstance(ds, RetrievalDataset)
            and ds.layout is Layout.DATABASE_QUERIES):
        from vpr_explorer.descriptors.vme_run import run_stamp

        return _names_key(ds) + run_stamp(path, ds)
    return _files_key(ds) if path is None else _names_key(ds)


def check_descriptor_file(text: str) -> Path:
    """A typed descriptor file path, checked before it is read: it lies under the app's data root, it
    exists, its extension is one the library reads (or it is a VPR-methods-evaluation run folder holding both
    its files), and its stem (the descriptor's name) names no extractor."""
    from vpr_explorer.descriptors.imported import descriptor_format
    from vpr_explorer.descriptors.registry import EXTRACTOR_NAMES

    if not str(text).strip():
        raise VPRInputError("descriptor file: type the path of a .npz, .npy or hloc .h5 file")
    path = under_data_root(str(text).strip(), what="descriptor file")
    if path.is_dir():  # a VPR-methods-evaluation run folder (descriptors.vme_run): both its .npy files there
        from vpr_explorer.descriptors.vme_run import check_run_folder

        check_run_folder(path)
    else:
        descriptor_format(path)  # an unknown extension, named
    if not path.is_file() and not path.is_dir():
        raise VPRInputError(f"descriptor file {path}: no such file; give the path of a .npz, .npy or hloc .h5 file "
                            "on this machine")
    if path.stem in EXTRACTOR_NAMES:
        raise VPRInputError(f"descriptor file {path}: its stem {path.stem!r} names a built-in descriptor; rename the "
                            "file (its stem names the descriptor in the app)")
    return path


def descriptor_path(descriptor: str, file: str | Path | None = None) -> Path | None:
    """The file a descriptor is read from: ``file`` (typed on the Dataset page), a file the app was
    started with (``descriptor_files``), or ``None`` for an extractor."""
    if file is not None:
        return check_descriptor_file(str(file))
    return descriptor_files().get(descriptor)


def _load_key(descriptor: str, files: str, path: Path | None = None, dataset_key: tuple = ()) -> tuple:
    """What ``load``'s result depends on: the images' ``files`` key, the layout and radius the
    dataset was read with (``dataset_key``), and the descriptor file (its size and mtime) or the cache mode."""
    if path is not None:
        try:
            s = path.stat()
            stamp = f"{s.st_size}|{s.st_mtime_ns}"
        except OSError:
            stamp = "missing"
        return ("imported", path.stem, str(path.resolve()), stamp, files, *dataset_key)
    # on_disk in the key: a cache folder that stops (or starts) being writable is not
    # stuck with a failure (or an in-memory result) remembered under the other mode.
    return ("descriptors", descriptor, files, *dataset_key, disk_cache_problem() is None)


def load(source: str, descriptor: str, *, layout: str = Layout.AUTO.value, radius: float | None = None,
         file: str | Path | None = None) -> Loaded:
    """The dataset and its descriptors, computed with a progress bar and time estimate if not in memory.

    Through the on-disk cache, or in memory only when the cache folder cannot be written;
    a descriptor file (``file``, typed on the Dataset page, or one the app was started with,
    ``descriptor_files``) is read instead, and named by its stem. The result's ``key``
    holds the file's content hash (``ImportedDescriptors.key``), the layout and the radius,
    so no cache below serves results of an edited file or another ground truth.
    """
    loaded = _load(source, descriptor, layout=layout, radius=radius, file=file)
    if loaded.descriptors.dtype == np.float16:  # a mapped database: its reads' cast is imported meanwhile
        stats.prepare_float16_reads()
    return loaded


def _load(source: str, descriptor: str, *, layout: str, radius: float | None, file: str | Path | None) -> Loaded:
    """``load``'s result, from the memo or computed."""
    from vpr_explorer.descriptors.custom import MODELS_ENV
    from vpr_explorer.descriptors.hub import is_hub_name

    if is_hub_name(descriptor):  # a link's descriptor= must never run a repository's code
        raise VPRInputError(f"descriptor {descriptor!r}: the app runs a torch.hub model only by a name of the "
                            f"models settings file ({MODELS_ENV}: [models.NAME] model = \"hub:DIR[:ENTRY]\"); "
                            "pick a descriptor from the Dataset page's list")
    ds = dataset(source, layout, radius)
    path = descriptor_path(descriptor, file)
    files = _images_key(ds, path)
    dataset_key = (layout, radius) if isinstance(ds, RetrievalDataset) else ()
    key = _load_key(descriptor, files, path, dataset_key)
    suffix = "".join(f"-{x}" for x in dataset_key)
    if path is not None:
        def read(_progress):
            imp = imported_descriptors(ds, path)
            return Loaded(ds, imp.name, imp.descriptors, f"{files[:16]}-{imp.key[:24]}{suffix}", imp.notes)

        return _memoised(key, f"Reading {path.name} for {ds.n_images} images", read)

    on_disk = key[-1]

    def compute(progress):
        if on_disk:  # a database/queries dataset past 1 GiB of float32 is mapped from the cache (float16)
            d = dataset_descriptors(ds, descriptor, progress=progress,
                                    **({"mmap": "auto"} if isinstance(ds, RetrievalDataset) else {}))
        else:
            d = extract_descriptors(list(ds.image_paths), get_extractor(descriptor), progress=progress)
        if not isinstance(d, np.memmap):  # a mapped float16 view stays mapped (read-only), never a float32 copy
            d = np.asarray(d, dtype=np.float32)  # already float32 and read-only: no copy
            if d.flags.writeable:
                d = d.copy()
                d.setflags(write=False)
        return Loaded(ds, descriptor, d, f"{files[:16]}-{fingerprint(d)[:24]}{suffix}")

    return _memoised(key, f"Computing {descriptor} descriptors of {ds.n_images} images", compute)


def loaded_in_memory(source: str, descriptor: str, *, layout: str = Layout.AUTO.value, radius: float | None = None,
                     file: str | Path | None = None) -> bool:
    """True when ``load`` would return at once (descriptors already in this server's memory)."""
    try:
        ds = dataset(source, layout, radius)
        dataset_key = (layout, radius) if isinstance(ds, RetrievalDataset) else ()
        path = descriptor_path(descriptor, file)
        return _memo().get(_load_key(descriptor, _images_key(ds, path), path, dataset_key)) is not None
    except VPRInputError:
        return False


# --------------------------------------------------------------------------- the dataset value


@st.cache_resource(show_spinner=False, max_entries=8)
def _value(key: str, query: str, database: tuple[str, ...] | None, tolerance: int, _data: Loaded) -> Loaded:
    value = database_queries(_data.dataset, query, database, tolerance)
    rows = value_rows(value)
    d = _data.descriptors
    if rows is not None:
        d = d[rows]
        d.setflags(write=False)
    chosen = "" if database is None and not tolerance else f"-database-{'+'.join(database or ())}-tolerance-{tolerance}"
    return Loaded(value, _data.descriptor, d, f"{key}-query-{query}{chosen}", _data.notes)


def value(data: Loaded, query: str, *, database: tuple[str, ...] | None = None, tolerance: int = 0) -> Loaded:
    """``data`` as one dataset value: aligned traversals become a database/queries dataset with ``query`` as the
    query traversal (``data.aligned.database_queries``: ``database`` traversals, default every other one, and
    right images within ``tolerance`` frames) and their descriptors in its order; any other layout is returned
    as it is."""
    if isinstance(data.dataset, RetrievalDataset):
        return data
    return _value(data.key, query, None if database is None else tuple(database), int(tolerance), data)


# --------------------------------------------------------------------------- derived results


def places_key(places: RetrievalPlaces) -> tuple:
    """``places`` as plain values (what Streamlit hashes) that ``_places`` turns back into it."""
    spec, metric = places.spec, places.metric
    return (None if places.geometry is None else places.geometry.value,
            None if spec is None else (spec.group, spec.step, spec.reading.value),
            None if metric is None else (metric.group, metric.step, metric.reading.value, metric.geometry.value))


def _places(key: tuple) -> RetrievalPlaces:
    geometry, spec, metric = key
    return RetrievalPlaces(None if geometry is None else PlaceGeometry(geometry),
                           None if spec is None else PlaceSpec(*spec), None if metric is None else MetricPlaceSpec(*metric))


@st.cache_resource(show_spinner="Fitting the database thresholds for these places…", max_entries=32)
def _fitted(key: str, places: tuple, _data: Loaded) -> RetrievalFitted:
    return views.fit_retrieval(_data.descriptors, _data.dataset, _places(places), device=fit_device())


def fitted(data: Loaded, places: RetrievalPlaces) -> RetrievalFitted:
    """Places of the database images and their thresholds: what one-place and one-query pages need."""
    return _fitted(data.key, places_key(places), data)


@st.cache_resource(show_spinner="Deciding the queries…", max_entries=32)
def _overview(key: str, places: tuple, _data: Loaded) -> tuple[RetrievalOverview, float]:
    start = time.perf_counter()
    f = _fitted(key, places, _data)
    return views.overview(f, _data.descriptors), time.perf_counter() - start


def overview_timed(data: Loaded, places: RetrievalPlaces) -> tuple[RetrievalOverview, float]:
    """The query images decided (a sample on big datasets) and the seconds it took when first asked for."""
    return _overview(data.key, places_key(places), data)


@st.cache_data(show_spinner=False, max_entries=256)
def _decision(key: str, places: tuple, query: int, k: float, user_theta, _data: Loaded) -> QueryDecision:
    f = _fitted(key, places, _data)
    return views.explain_query(f, _data.descriptors, query, k=k, user_theta=user_theta)


def decision(data: Loaded, places: RetrievalPlaces, query: int, *, k: float = 0.0,
             user_theta: float | None = None) -> QueryDecision:
    """The decision record of one query image under every method."""
    return _decision(data.key, places_key(places), int(query), float(k), user_theta, data)


# a resource (returned as is, never mutated): its negative scores are n_p × the database images in
# places (millions of floats on a large database), which st.cache_data would copy on every rerun
@st.cache_resource(show_spinner="Scoring the place's images…", max_entries=8)
def _detail(key: str, places: tuple, place: int, _data: Loaded) -> views.PlaceDetail:
    return views.place_detail(_fitted(key, places, _data), _data.descriptors, place)


def detail(data: Loaded, places: RetrievalPlaces, place: int) -> views.PlaceDetail:
    """One place's negative mixture, scores and thresholds, and its queries' raw_p (``views.place_detail``)."""
    return _detail(data.key, places_key(places), int(place), data)


@st.cache_data(show_spinner=False, max_entries=256)
def _image_answer(key: str, query: int, _data: Loaded) -> views.ImageAnswer:
    return views.image_answer(_data.dataset, _data.descriptors, query)


def image_answer(data: Loaded, query: int) -> views.ImageAnswer:
    """The query's top database image over all of them (the field's image-level answer)."""
    return _image_answer(data.key, int(query), data)


@st.cache_data(show_spinner=False, max_entries=256)
def _found(key: str, places: tuple, after: int, kind: str, method: str, direction: str, k: float, user_theta,
           _data: Loaded) -> tuple[int | None, int]:
    f = _fitted(key, places, _data)
    return views.find_query(f, _data.descriptors, after=after, kind=kind, method=method, direction=direction, k=k,
                            user_theta=user_theta)


def find(data: Loaded, places: RetrievalPlaces, *, after: int, kind: str, method: str, direction: str = "next",
         k: float = 0.0, user_theta: float | None = None) -> tuple[int | None, int]:
    """``numbers.find_query``: the first query of kind ``kind`` under ``method`` from ``after``, walking ``direction``."""
    return _found(data.key, places_key(places), int(after), kind, method, str(direction), float(k), user_theta, data)


@st.cache_resource(show_spinner=False, max_entries=1)
def _shared(key: str, _data: Loaded) -> SharedScores | None:
    return SharedScores(_data.descriptors) if len(_data.descriptors) <= SHARED_LIMIT else None


def shared_scores(data: Loaded) -> SharedScores | None:
    """The scores every protocol run on ``data`` shares (``shared_scores.SharedScores``), kept for the
    latest descriptors: a second protocol, run or sweep on them computes no similarity or Gram again.
    ``None`` above ``SHARED_LIMIT`` images (the protocols use the closed form there)."""
    return _shared(data.key, data)


def evaluation(data: Loaded, spec: PlaceSpec | None, protocol: str, *, peek: bool = False,
               **options) -> Evaluation | None:
    """A protocol run on aligned traversals (see ``pipeline.run_protocol``), with a progress bar the first time.

    ``peek``: only a run already in this server's memory, ``None`` when it has not been
    computed (nothing is run): how a page decides whether showing it costs anything.
    """
    from vpr_explorer.method.places import make_places
    from vpr_explorer.protocols.options import ProtocolOptions

    places = make_places(data.dataset, spec)
    run = ProtocolOptions(**options)
    key = ("evaluation", data.key, None if spec is None else (spec.group, spec.step, spec.reading.value), protocol, run)
    if peek:
        hit = _memo().get(key)
        return hit if isinstance(hit, Evaluation) else None
    return _memoised(key, f"Running the {protocol} protocol", lambda progress: run_protocol(
        protocol, data.dataset, places, data.descriptors, run, progress=progress,
        settings={"descriptor": data.descriptor}, shared=shared_scores(data)))


def _queries_evaluation_key(data: Loaded, places: RetrievalPlaces, user_theta: float | None, pr: bool) -> tuple:
    return ("retrieval-evaluation", data.key, places_key(places), user_theta, pr)


def queries_evaluated(data: Loaded, places: RetrievalPlaces, *, user_theta: float | None = None,
                      pr: bool = False) -> bool:
    """True when ``queries_evaluation`` would return at once (already run in this server)."""
    return _memo().get(_queries_evaluation_key(data, places, user_theta, pr)) is not None


def queries_evaluation(data: Loaded, places: RetrievalPlaces, *, user_theta: float | None = None,
                       pr: bool = False) -> Evaluation:
    """The database/queries protocol (``pipeline.evaluate_retrieval``) on a dataset value, with a progress bar
    the first time."""
    from vpr_explorer.protocols.options import ProtocolOptions

    options = ProtocolOptions(user_theta=user_theta, pr=pr)
    key = _queries_evaluation_key(data, places, user_theta, pr)
    return _memoised(key, "Running the database/queries protocol", lambda progress: evaluate_retrieval(
        data.dataset, data.descriptors, options, spec=places.spec, metric=places.metric,
        settings={"descriptor": data.descriptor}, progress=progress))


@st.cache_resource(show_spinner="Computing the similarity matrix…", max_entries=4)
def _similarity_grid(key: str, _data: Loaded) -> views.SimilarityGrid:
    return views.similarity_grid(_data.dataset, _data.descriptors)


def similarity_grid(data: Loaded) -> views.SimilarityGrid:
    """The value's queries × database images similarity, pooled (``numbers.similarity_grid``)."""
    return _similarity_grid(data.key, data)


# --------------------------------------------------------------------------- images


@st.cache_data(show_spinner=False, max_entries=2048)
def _thumbnail(path: str, mtime_ns: int, height: int) -> bytes | None:
    try:
        image = open_image(Path(path), "RGB", display_size=(height * 2, height))
    except VPRInputError:
        return None
    image.thumbnail((height * 4, height))
    buf = io.BytesIO()
    image.save(buf, format="JPEG", quality=85)
    return buf.getvalue()


def thumbnail(path: Path, height: int = 96) -> bytes | Image.Image:
    """A small JPEG of an image, or a grey placeholder when it cannot be read."""
    try:
        mtime = path.stat().st_mtime_ns
    except OSError:
        mtime = -1
    data = _thumbnail(str(path), mtime, height)
    return data if data is not None else Image.new("RGB", (height * 16 // 9, height), (200, 200, 200))


def clear_all() -> None:
    """Forget every cached result of this server (the on-disk descriptor cache stays)."""
    st.cache_data.clear()
    st.cache_resource.clear()


# --------------------------------------------------------------------------- the acceptance bench


@st.cache_resource(show_spinner="Running every acceptance rule on the whole similarity matrix…", max_entries=8)
def _bench(key: str, places: tuple, options: tuple, _data: Loaded, _options: BenchOptions) -> AcceptanceReport:
    ds = _data.dataset
    place = _places(places)
    labels, _ = retrieval_places(ds, place.spec, place.metric) if ds.database_place is None else (
        ds.database_place, 0)
    return acceptance_report(ds, _data.descriptors, labels=labels, options=_options,
                             settings={"descriptor": _data.descriptor, "group/step": place.describe(ds)})


def bench(data: Loaded, places: RetrievalPlaces, options: BenchOptions) -> AcceptanceReport:
    """Every acceptance rule on the value's queries, closed set and natural open set (``protocols.acceptance``).

    Args:
        data: a dataset value (``value``: for aligned traversals, pick one database traversal and
            the tolerance the ground truth counts, so that the sequence rules apply).
        places: the group/step places of the per-place rules (unless ``options.places`` is discovered).
        options: the bench's choices.
    """
    return _bench(data.key, places_key(places), options_key(options), data, options)


def options_key(options: BenchOptions) -> tuple:
    """The bench's options as plain values, what Streamlit hashes for a cache key (``taus`` is a mapping)."""
    return tuple((f.name, repr(getattr(options, f.name))) for f in dataclasses.fields(options))
