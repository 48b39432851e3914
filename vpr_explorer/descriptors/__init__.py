"""Global image descriptors: extractors by name, extraction through an on-disk cache.

Stage 3 of the data flow (datasets -> places -> **descriptors** -> statistics): turns
image files into an ``(n_images, D)`` float32 matrix of L2-normalised rows, so that a dot
product is the cosine similarity the thresholds are built on. Descriptors belong to
images, not places: regrouping never recomputes them.

Built in: ``pixels``, ``efficientnet-lite0`` and the paper's ``alexnet-conv3``,
``cosplace`` and ``eigenplaces`` (their weights: :mod:`.checkpoints`); users add their
own models with :func:`register_extractor` or a ``VPR_EXPLORER_MODELS`` settings file
(:mod:`.custom`). Descriptors computed elsewhere come in through
:func:`load_descriptor_file` (:mod:`.imported`). Extraction on a Ray cluster, into the same
cache, is :mod:`.distributed` (the optional ``ray`` extra; not imported here).
"""

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.descriptors.cache import CacheHits, DescriptorCache, DescriptorCacheWarning
from vpr_explorer.descriptors.extract import ExtractionInterrupted, extract_descriptors, fingerprint
from vpr_explorer.descriptors.imported import (
    DescriptorFormat,
    ImportedDescriptors,
    descriptor_format,
    load_descriptor_file,
    relative_names,
    write_descriptor_file,
)
from vpr_explorer.descriptors.registry import (
    EXTRACTOR_NAMES,
    available_extractors,
    extractor_names,
    get_extractor,
    register_extractor,
    unregister_extractor,
)

__all__ = [
    "EXTRACTOR_NAMES",
    "CacheHits",
    "DescriptorCache",
    "DescriptorCacheWarning",
    "DescriptorFormat",
    "ExtractionInterrupted",
    "Extractor",
    "ImportedDescriptors",
    "available_extractors",
    "descriptor_format",
    "extract_descriptors",
    "extractor_names",
    "fingerprint",
    "get_extractor",
    "load_descriptor_file",
    "register_extractor",
    "relative_names",
    "unregister_extractor",
    "write_descriptor_file",
]
