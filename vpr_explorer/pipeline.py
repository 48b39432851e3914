"""The stages wired together: dataset -> places -> descriptors -> protocol.

What the command line, the app and the recorder call, so that each of them is
"arguments -> one call -> render".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from vpr_explorer.data.aligned import database_queries, value_rows
from vpr_explorer.data.traversals import Dataset, load_dataset
from vpr_explorer.descriptors.hub import hub_settings
from vpr_explorer.errors import VPRInputError
from vpr_explorer.protocols.evaluation import (
    Evaluation,
    Progress,
    Protocol,
    open_set_protocol,
    retrieval_protocol,
)
from vpr_explorer.method.places import Places, PlaceSpec, make_places, retrieval_places
from vpr_explorer.protocols.options import ProtocolOptions, check_whole
from vpr_explorer.protocols.scale import fast_paper_protocol
from vpr_explorer.protocols.shared_scores import SharedScores
from vpr_explorer.settings import check_cache_root, default_workers

DEMO = "demo"


def resolve_dataset(source: str | Path) -> Dataset:
    """``"demo"`` (the built-in procedural route) or a dataset folder in either layout."""
    if str(source) == DEMO:
        from vpr_explorer.data.demo import demo_dataset

        return demo_dataset()
    return load_dataset(source)


def dataset_descriptors(
    dataset: Dataset,
    descriptor: str,
    *,
    cache_root: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    batch_size: int = 32,
    dtype: str = "float32",
    storage: str | None = None,
    mmap: bool | str = False,
    options: Mapping[str, object] | None = None,
) -> np.ndarray:
    """``(n_images, D)`` L2-normalised descriptors of every image, through the on-disk cache.

    Args:
        options: the extractor's options, ``get_extractor(descriptor, **options)`` (a
            ``hub:DIR[:ENTRY]`` model's ``hub_args``, ``input_size``...: they are part of its
            cache key, so the same options find what ``vpr-explorer extract`` cached).
        cache_root: cache folder; default ``settings.cache_root() / "descriptors"``.
        dtype: ``"float32"`` or ``"float16"``, the in-memory dtype of the result; float16
            halves it (563 -> 282 MB at 110,000 x 1,280), at ~1e-3 relative error.
        storage: the dtype new vectors are cached in on disk; default ``dtype``. A
            float16 cache reads shards of either dtype; a float32 one only float32 shards,
            so a float32 run after a float16 one recomputes rather than return rounded vectors.
        mmap: ``True``: once every image is cached, the result is the cache's float16
            dataset view (``DescriptorCache.dataset_view``: written once, then memory-mapped;
            a million images × 2,048 are 4 GB on disk and never a float32 copy in memory),
            whatever ``dtype``; ``"auto"``: the same once the float32 copy would reach
            ``descriptors.store.mmap_min_bytes()``; ``False`` (default): in memory.

    Returns:
        ``(n_images, D)`` in ``dtype`` (float16 memmap when mapped), read-only.

    Raises:
        VPRInputError: naming ``dtype`` or ``storage`` when not float32/float16, or what
            :func:`extract_descriptors` raises.
    """
    from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
    from vpr_explorer.descriptors.cache import check_dtype

    from vpr_explorer.descriptors.store import check_mmap, wants_mmap

    dtype = check_dtype(dtype, "dtype")
    storage = dtype if storage is None else check_dtype(storage, "storage", "cache storage type")
    mmap = check_mmap(mmap)
    extractor = get_extractor(descriptor, **dict(options or {}))
    cache = DescriptorCache(cache_root, dtype=storage)
    paths = list(dataset.image_paths)
    if mmap == "off" or not wants_mmap(mmap, len(paths), extractor.dim):
        return extract_descriptors(paths, extractor, cache=cache, batch_size=batch_size, progress=progress,
                                   dtype=dtype)
    return cached_view(paths, extractor, cache, batch_size=batch_size, progress=progress)


def cached_view(paths: Sequence[Path], extractor, cache, *, batch_size: int = 32,
                progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """The float16 memmap of ``paths``' descriptors from ``cache`` (``DescriptorCache.dataset_view``).

    Images not cached yet are extracted first, into the cache, a ``VIEW_BATCH`` at a time (the
    vectors are dropped as they go: the view is then written from the shards).
    """
    from concurrent.futures import ThreadPoolExecutor

    from vpr_explorer.descriptors import extract_descriptors
    from vpr_explorer.descriptors.extract import hash_paths

    cache.check_writable()
    with ThreadPoolExecutor(max_workers=default_workers()) as pool:
        hashes = hash_paths(paths, pool)
    view = cache.dataset_view(extractor.cache_key, hashes)
    if view is None:
        missing = np.flatnonzero(~cache.contains(extractor.cache_key, hashes))
        for lo in range(0, len(missing), VIEW_BATCH):
            part = missing[lo:lo + VIEW_BATCH]
            extract_descriptors([paths[i] for i in part], extractor, cache=cache, batch_size=batch_size,
                                dtype="float16",
                                progress=None if progress is None else
                                (lambda done, total, lo=lo: progress(len(paths) - len(missing) + lo + done,
                                                                     len(paths))))
        view = cache.dataset_view(extractor.cache_key, hashes)
        if view is None:  # pragma: no cover (every image was just cached)
            raise VPRInputError(f"{cache.root}: descriptors just extracted are missing from the cache; "
                                "is another process clearing it?")
    if progress:
        progress(len(paths), len(paths))
    return view


VIEW_BATCH = 65_536
"""Images extracted per call before a dataset view is written (their vectors are not kept)."""


def default_traversals(dataset: Dataset, database: Sequence[str] | None, queries: str | None) -> tuple[list[int], int]:
    """Database and query traversal indices; by default ``Dataset.default_roles`` (names, else folder order)."""
    if dataset.n_traversals < 2:
        raise VPRInputError(f"{dataset.name!r} has one traversal: the traversal protocol needs a second to query with")
    roles = dataset.default_roles()
    db = [dataset.traversal_index(t) for t in database] if database else None
    if queries is not None:
        q = dataset.traversal_index(queries)
    elif db is not None and roles.query in db:
        # the default query traversal was named as a database: query with the last one left
        q = max((t for t in range(dataset.n_traversals) if t not in db), default=roles.query)
    else:
        q = roles.query
    if db is None:
        db = [t for t in roles.database if t != q] or [0 if q != 0 else 1]
    if q in db:
        raise VPRInputError(f"queries={dataset.traversals[q]!r} is also a database traversal; pick another query "
                            "traversal")
    return db, q


def traversal_direction(dataset: Dataset, database: Sequence[int], query: int) -> str:
    """How the traversal protocol's direction was chosen, in words (for its settings and header)."""
    roles = dataset.default_roles()
    if list(database) != list(roles.database) or query != roles.query:
        return "as given"
    return ("default, recognised from the traversal names" if roles.by_name
            else "default by folder order: the first traversal against the last (pick with database/queries)")


def _protocol(protocol: Protocol | str) -> Protocol:
    try:
        return Protocol(protocol)
    except ValueError:
        raise VPRInputError(f"protocol {protocol!r}: choose one of {', '.join(p.value for p in Protocol)}") from None


def options_of(options: ProtocolOptions | None, fields: dict) -> ProtocolOptions:
    """``options``, or the ``ProtocolOptions`` of ``fields`` (its field names as keywords) when it is None.

    Raises:
        VPRInputError: both were given.
    """
    if options is None:
        return ProtocolOptions(**fields)
    if fields:
        raise VPRInputError(f"{', '.join(fields)}: give the options as one ProtocolOptions or as keywords, not both")
    return options


def check_options(protocol: Protocol | str, dataset: Dataset, options: ProtocolOptions | None = None,
                  **fields) -> Protocol:
    """Check what a protocol's options mean for ``dataset``, cheaply, so that bad input fails before any work.

    ``ProtocolOptions`` checks each value on its own; here the protocol's name, the tolerance
    against the dataset's frames and the traversal protocol's traversals are checked.
    ``fields``: ``ProtocolOptions``' fields as keywords, in place of ``options``.

    Raises:
        VPRInputError: naming the option, its value and the limit or the fix.
    """
    protocol = _protocol(protocol)
    options = options_of(options, fields)
    check_whole("tolerance", options.tolerance, low=0, high=dataset.n_frames,
                why=f" (frames of slack; {dataset.name!r} has {dataset.n_frames:,} frames)")
    if protocol is Protocol.TRAVERSAL:
        default_traversals(dataset, options.database, options.queries)
    return protocol


def run_protocol(
    protocol: Protocol | str,
    dataset: Dataset,
    places: Places,
    descriptors: np.ndarray,
    options: ProtocolOptions | None = None,
    *,
    progress: Progress | None = None,
    settings: dict | None = None,
    shared: SharedScores | None = None,
    **fields,
) -> Evaluation:
    """Run one protocol of ``evaluation`` on a dataset's descriptors.

    Options are checked first (``check_options``). The result's settings hold every option
    that shaped the run: group/step/reading, the user's θ and the tolerance beside the
    protocol's own (runs, seed, …). The traversal protocol is the database/queries protocol
    (``evaluation.retrieval_protocol``) on the aligned traversals' value
    (``data.aligned.database_queries``), its settings naming the traversals.

    Args:
        options: the protocol's settings (default ``ProtocolOptions()``); or ``fields``, its
            field names as keywords.
        settings: what the caller records in the result's settings (the descriptor, …).
        shared: the ``shared_scores.SharedScores`` of these descriptors, to reuse between
            runs of the paper and open-set protocols (a sweep's cells); the numbers are the
            same without.
    """
    options = options_of(options, fields)
    protocol = check_options(protocol, dataset, options)
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(
            f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: recompute them"
        )
    if shared is not None:
        shared.check(descriptors)
    spec = places.spec
    settings = {
        "dataset": dataset.name, "places": places.describe(), **(settings or {}),
        "group": spec.group if spec else None, "step": spec.step if spec else None,
        "reading": spec.reading.value if spec else None, "theta": options.user_theta, "tolerance": options.tolerance,
    }
    if protocol is Protocol.TRAVERSAL:
        return _traversal(dataset, places, descriptors, options, settings, progress)
    pooled = dict(image_frame=dataset.image_frame, frame_place=places.frame_place, progress=progress,
                  settings=settings, shared=shared)
    if protocol is Protocol.PAPER:
        # evaluation.paper_protocol's numbers (tests/test_scale.py) in one pass over the image pairs
        return fast_paper_protocol(descriptors, places.image_place, dataset.image_traversal, places.n_places, options,
                                   **pooled)
    return open_set_protocol(descriptors, places.image_place, dataset.image_traversal, places.n_places, options,
                             **pooled)


def _traversal(dataset: Dataset, places: Places, descriptors: np.ndarray, options: ProtocolOptions, settings: dict,
               progress: Progress | None) -> Evaluation:
    """The traversal protocol: ``retrieval_protocol`` on the value of the chosen traversals, labelled as such.

    The settings name the database and query traversals, the direction's origin, the
    database's places, the query frames scored and those between places.
    """
    db, q = default_traversals(dataset, options.database, options.queries)
    value = database_queries(dataset, query=q, database=db, tolerance=options.tolerance)
    rows = value_rows(value)
    d = descriptors if rows is None else descriptors[rows]
    ev = retrieval_protocol(d[:value.n_database], d[value.n_database:], places.frame_place[value.database_frame],
                            places.n_places, value.ground_truth, options, progress=progress)
    between = ev.settings["queries_between_places"]
    return dataclasses.replace(ev, protocol=Protocol.TRAVERSAL, settings={
        **settings, "places": places.describe(images=np.flatnonzero(np.isin(dataset.image_traversal, db)),
                                              what="database images"),
        "direction": traversal_direction(dataset, db, q), "database": [dataset.traversals[t] for t in db],
        "queries": dataset.traversals[q], "queries_scored": ev.settings["queries"] - between,
        "queries_between_places": between,
    })


def evaluate_dataset(
    source: str | Path,
    spec: PlaceSpec | None,
    descriptor: str,
    protocol: Protocol | str,
    options: ProtocolOptions | None = None,
    *,
    cache_root: Path | None = None,
    extract_progress: Callable[[int, int], None] | None = None,
    progress: Progress | None = None,
    dtype: str = "float32",
    storage: str | None = None,
    layout: str = "auto",
    descriptors_file: Path | None = None,
    names_file: Path | None = None,
    descriptor_options: Mapping[str, object] | None = None,
    **fields,
) -> Evaluation:
    """Everything from a dataset path (or ``"demo"``) to an ``Evaluation``.

    ``dtype``, ``storage`` and ``descriptor_options`` (the extractor's) go to
    :func:`dataset_descriptors`; ``options`` (or ``fields``, its field names as keywords) and
    ``progress`` to :func:`run_protocol`. With
    ``descriptors_file``, descriptors computed elsewhere are read
    from it (:func:`imported_descriptors`) instead of ``descriptor``'s extraction, the
    file's stem names the descriptor, and the settings record the file's path and sha256
    (``ImportedDescriptors.settings``); an extractor's ``descriptor_options``, when given, are
    recorded after its name as the ``--hub-*`` flags that give them
    (``descriptors.hub.hub_settings``).
    """
    if descriptors_file is None:
        check_cache_root(cache_root)  # an unusable cache folder fails before the dataset is read or the demo drawn
    dataset = open_dataset(source, layout) if layout != "auto" else resolve_dataset(source)
    if not isinstance(dataset, Dataset):
        raise VPRInputError(f"{source} is a {dataset.layout.value} layout: evaluate it with evaluate_retrieval")
    places = make_places(dataset, spec)
    options = options_of(options, fields)
    check_options(protocol, dataset, options)
    source: dict[str, str] = {}
    if descriptors_file is not None:
        imp = imported_descriptors(dataset, descriptors_file, names_file=names_file, dtype=dtype)
        desc, descriptor, source = imp.descriptors, imp.name, imp.settings()
    else:
        desc = dataset_descriptors(
            dataset, descriptor, cache_root=cache_root, progress=extract_progress, dtype=dtype, storage=storage,
            options=descriptor_options,
        )
        source = hub_settings(descriptor_options or {})
    return run_protocol(protocol, dataset, places, desc, options, progress=progress,
                        settings={"descriptor": descriptor, **source, "dtype": str(desc.dtype)})


def imported_descriptors(dataset, path: Path, *, names_file: Path | None = None, dtype: str = "float32",
                         mmap: bool | str = "auto"):
    """Descriptors computed elsewhere, read from ``path`` in ``dataset``'s image order (:mod:`.descriptors.imported`).

    Works for a ``Dataset`` and a ``layouts.RetrievalDataset`` alike (both list ``image_paths``
    and a ``root``); the result's ``name`` (the file's stem) names the descriptor, its
    ``key`` (a content hash) keys any cache of results.

    A ``.npy`` (float16 or float32) whose rows are in the dataset's order is memory-mapped as
    stored (``descriptors.store.open_npy``, whatever ``dtype``) when ``mmap`` is ``True``, or
    ``"auto"`` (default), the dataset is a database/queries one (``layouts.RetrievalDataset``,
    whose views and protocol read a map in blocks) and the file's float32 copy would reach
    ``store.mmap_min_bytes()`` (1 GiB): a million-image database is never copied into memory.
    Any other file is read into memory in ``dtype`` (``load_descriptor_file``). A folder is a
    VPR-methods-evaluation run (``descriptors.vme_run``): its two ``.npy`` files, read into memory.
    """
    from vpr_explorer.descriptors.imported import load_descriptor_file, npy_header
    from vpr_explorer.descriptors.store import check_mmap, open_npy, wants_mmap
    from vpr_explorer.descriptors.vme_run import is_run_folder, load_vme_run
    from vpr_explorer.data.layouts import RetrievalDataset

    if is_run_folder(path):
        return load_vme_run(path, dataset, names_file=names_file, dtype=dtype)
    mode = check_mmap(mmap)
    if mode == "auto" and not isinstance(dataset, RetrievalDataset):
        mode = "off"
    if mode != "off" and Path(path).suffix.lower() == ".npy":
        try:
            shape = npy_header(Path(path).expanduser())[0]  # the header alone, checked against the file's size
        except VPRInputError:
            shape = ()  # load_descriptor_file names what is wrong with it
        if len(shape) == 2 and wants_mmap(mode, shape[0], shape[1]):
            found = open_npy(path, dataset.image_paths, dataset.root, names_file=names_file)
            if found is not None:
                return found
    return load_descriptor_file(path, dataset.image_paths, dataset.root, names_file=names_file, dtype=dtype)


# --------------------------------------------------------------------------- benchmark layouts (database and queries)


def open_dataset(source: str | Path, layout: str = "auto", *, radius: float | None = None,
                 database: Sequence[str] | None = None, queries: str | None = None, within: Path | None = None):
    """A ``Dataset`` (aligned traversals, prepared places, ``"demo"``) or a ``layouts.RetrievalDataset``.

    ``layout`` is ``auto`` (detected, see ``layouts.detect_layout``) or one of ``layouts.Layout``.
    ``radius`` (metres, default 25) is checked whatever the layout (``groundtruth.check_radius``);
    aligned traversals refuse it, and VPR-Bench and a manifest's place ids do not read it
    (``layouts.radius_applies``: the command line refuses it there). ``within`` (the app's
    data root): a manifest may name images only under it (``layouts.load_manifest``).

    Raises:
        VPRInputError: naming the path, file, line or option at fault; an entry of the dataset
            folder that cannot be read (no permission, a symbolic link to nothing) is named.
    """
    from vpr_explorer.data.traversals import reading
    from vpr_explorer.data.groundtruth import DEFAULT_RADIUS, check_radius
    from vpr_explorer.data.layouts import RETRIEVAL_LAYOUTS, Layout, detect_layout, load_retrieval

    try:
        layout = Layout(layout)
    except ValueError:
        raise VPRInputError(f"layout {layout!r}: choose one of {', '.join(x.value for x in Layout)}") from None
    if radius is not None:
        check_radius(radius, "radius")
    if str(source) == DEMO:
        if layout not in (Layout.AUTO, Layout.TRAVERSALS):
            raise VPRInputError(f"--layout {layout.value}: the demo route is traversal folders")
        if radius is not None:
            raise VPRInputError("--radius applies to position-tagged layouts; the demo route is traversal folders")
        return resolve_dataset(source)
    path = Path(source).expanduser()
    with reading(path):
        if not path.exists():
            raise VPRInputError(f"{path}: the dataset folder does not exist; check the path")
    if layout is Layout.AUTO:
        layout = detect_layout(path)
    if layout in RETRIEVAL_LAYOUTS:
        return load_retrieval(path, layout, radius=DEFAULT_RADIUS if radius is None else radius,
                              database=list(database) if database else None, queries=queries, within=within)
    if radius is not None:
        raise VPRInputError(f"--radius applies to position-tagged layouts; {path} is read as {layout.value}")
    dataset = load_dataset(path)
    if layout is Layout.PREPARED and dataset.prepared_places is None:
        raise VPRInputError(f"{path}: --layout prepared needs images named Place####_Cond##_G##")
    return dataset


def evaluate_retrieval(
    dataset,
    descriptors: np.ndarray,
    options: ProtocolOptions | None = None,
    *,
    spec: PlaceSpec | None = None,
    metric=None,
    settings: dict | None = None,
    progress: Progress | None = None,
    **fields,
) -> Evaluation:
    """The database/queries protocol on a ``RetrievalDataset`` with its descriptors (database rows first).

    Reads ``options``' user_theta and pr (or ``fields``, its field names as keywords).

    In-memory float32 descriptors go to ``evaluation.retrieval_protocol``. A memory-mapped
    (or float16) matrix, such as a million-image database (``descriptors.store``), goes to
    ``numbers.evaluate_fitted``: the same table, the database read a block at a time
    and never converted whole, with the thresholds of the explorer's (kept) fit of these places.
    """
    options = options_of(options, fields)
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: "
                            "recompute them")
    user_theta = options.user_theta
    place, n_places = retrieval_places(dataset, spec, metric)
    how = ("places from the layout" if dataset.database_place is not None
           else metric.describe() if metric is not None else spec.describe())
    settings = {"dataset": dataset.name, "layout": dataset.layout.value, "places": f"{n_places} places ({how})",
                **({"theta": user_theta} if user_theta is not None else {}), **(settings or {})}
    from vpr_explorer.views import numbers as rv

    if not rv.dense(descriptors):
        geometry = None if dataset.database_place is not None else (
            metric.geometry if metric is not None else rv.PlaceGeometry.FRAMES)
        fitted = rv.fit_retrieval(descriptors, dataset, rv.RetrievalPlaces(
            geometry, None if metric is not None else spec, metric))
        return rv.evaluate_fitted(fitted, descriptors, user_theta=user_theta, settings=settings, progress=progress,
                                  pr=options.pr)
    d = np.asarray(descriptors)
    return retrieval_protocol(d[:dataset.n_database], d[dataset.n_database:], place, n_places, dataset.ground_truth,
                              options, progress=progress, settings=settings)
