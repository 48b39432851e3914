"""The stages wired together: dataset -> places -> descriptors -> protocol.

What the command line, the app and the recorder call, so that each of them is
"arguments -> one call -> render".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from vpr_explorer.datasets import Dataset, load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.evaluation import (
    K_GRID,
    Evaluation,
    Progress,
    Protocol,
    open_set_protocol,
    traversal_protocol,
)
from vpr_explorer.places import Places, PlaceSpec, make_places
from vpr_explorer.scale import fast_paper_protocol

DEMO = "demo"


def resolve_dataset(source: str | Path) -> Dataset:
    """``"demo"`` (the built-in procedural route) or a dataset folder in either layout."""
    if str(source) == DEMO:
        from vpr_explorer.demo import demo_dataset

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
) -> np.ndarray:
    """``(n_images, D)`` L2-normalised descriptors of every image, through the on-disk cache.

    Args:
        cache_root: cache folder; default ``settings.cache_root() / "descriptors"``.
        dtype: ``"float32"`` or ``"float16"``, the in-memory dtype of the result; float16
            halves it (563 -> 282 MB at 110,000 x 1,280), at ~1e-3 relative error.
        storage: the dtype new vectors are cached in on disk; default ``dtype``. A
            float16 cache reads shards of either dtype; a float32 one only float32 shards,
            so a float32 run after a float16 one recomputes rather than return rounded vectors.

    Returns:
        ``(n_images, D)`` in ``dtype``, read-only.

    Raises:
        VPRInputError: naming ``dtype`` or ``storage`` when not float32/float16, or what
            :func:`extract_descriptors` raises.
    """
    from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
    from vpr_explorer.descriptors.cache import check_dtype

    dtype = check_dtype(dtype, "dtype")
    storage = dtype if storage is None else check_dtype(storage, "storage", "cache storage type")
    extractor = get_extractor(descriptor)
    return extract_descriptors(
        list(dataset.image_paths), extractor, cache=DescriptorCache(cache_root, dtype=storage),
        batch_size=batch_size, progress=progress, dtype=dtype,
    )


def default_traversals(dataset: Dataset, database: Sequence[str] | None, queries: str | None) -> tuple[list[int], int]:
    """Database and query traversal indices; by default the first traversal against the last."""
    if dataset.n_traversals < 2:
        raise VPRInputError(f"{dataset.name!r} has one traversal: the traversal protocol needs a second to query with")
    q = dataset.traversal_index(queries) if queries is not None else dataset.n_traversals - 1
    db = [dataset.traversal_index(t) for t in database] if database else [0 if q != 0 else 1]
    return db, q


def _protocol(protocol: Protocol | str) -> Protocol:
    try:
        return Protocol(protocol)
    except ValueError:
        raise VPRInputError(f"protocol {protocol!r}: choose one of {', '.join(p.value for p in Protocol)}") from None


def check_options(protocol: Protocol | str, dataset: Dataset, *, runs: int = 50, database=None, queries=None,
                  **_) -> None:
    """Cheap checks of a protocol's options, so that bad input fails before descriptor extraction."""
    if _protocol(protocol) is Protocol.TRAVERSAL:
        default_traversals(dataset, database, queries)
    elif isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise VPRInputError(f"runs={runs!r}: must be a whole number, 1 or more")


def run_protocol(
    protocol: Protocol | str,
    dataset: Dataset,
    places: Places,
    descriptors: np.ndarray,
    *,
    runs: int = 50,
    seed: int = 0,
    cross_condition: bool = False,
    unknown_share: float = 0.3,
    database: Sequence[str] | None = None,
    queries: str | None = None,
    tolerance: int = 0,
    user_theta: float | None = None,
    k_grid: Sequence[float] = K_GRID,
    progress: Progress | None = None,
    settings: dict | None = None,
) -> Evaluation:
    """Run one protocol of ``evaluation`` on a dataset's descriptors."""
    protocol = _protocol(protocol)
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(
            f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: recompute them"
        )
    settings = {"dataset": dataset.name, "places": places.describe(), **(settings or {})}
    common = dict(user_theta=user_theta, settings=settings)
    if protocol is Protocol.TRAVERSAL:
        db, q = default_traversals(dataset, database, queries)
        return traversal_protocol(
            descriptors, places.image_place, dataset.image_traversal, dataset.image_frame, places.frame_place,
            database=db, query=q, tolerance=tolerance, traversal_names=dataset.traversals, **common,
        )
    pooled = dict(runs=runs, seed=seed, cross_condition=cross_condition, progress=progress, **common)
    if protocol is Protocol.PAPER:
        # evaluation.paper_protocol's numbers (tests/test_scale.py) in one pass over the image pairs
        return fast_paper_protocol(descriptors, places.image_place, dataset.image_traversal, places.n_places, **pooled)
    return open_set_protocol(
        descriptors, places.image_place, dataset.image_traversal, places.n_places,
        unknown_share=unknown_share, k_grid=k_grid, **pooled,
    )


def evaluate_dataset(
    source: str | Path,
    spec: PlaceSpec | None,
    descriptor: str,
    protocol: Protocol | str,
    *,
    cache_root: Path | None = None,
    extract_progress: Callable[[int, int], None] | None = None,
    dtype: str = "float32",
    storage: str | None = None,
    **options,
) -> Evaluation:
    """Everything from a dataset path (or ``"demo"``) to an ``Evaluation``.

    ``dtype`` and ``storage`` go to :func:`dataset_descriptors`, the other options to
    :func:`run_protocol`.
    """
    dataset = resolve_dataset(source)
    places = make_places(dataset, spec)
    check_options(protocol, dataset, **options)
    desc = dataset_descriptors(
        dataset, descriptor, cache_root=cache_root, progress=extract_progress, dtype=dtype, storage=storage
    )
    return run_protocol(protocol, dataset, places, desc, settings={"descriptor": descriptor, "dtype": str(desc.dtype)},
                        **options)
