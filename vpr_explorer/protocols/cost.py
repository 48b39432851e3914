"""What a protocol run costs, said before it runs: the image pairs it scores."""

from __future__ import annotations

from vpr_explorer.method.places import Places
from vpr_explorer.protocols.options import RUNS, UNKNOWN_SHARE


def protocol_pairs(protocol: str, places: Places | None, dataset, *, runs: int = RUNS, database=None,
                   unknown_share: float = UNKNOWN_SHARE, **_) -> int:
    """Image pairs a protocol run scores: its cost, to say before running it.

    Paper: one pass over all pairs of place images (``scale.fast_paper_protocol``).
    Open set: per split, each query against the training images. Traversal: each query
    frame against the database images. Database/queries: each query against every
    database image (``dataset`` is the value, ``places`` is not read).

    Args:
        protocol: a ``evaluation.Protocol`` value.
        places: the places of aligned traversals (``places.make_places``).
        dataset: the aligned traversals (``traversals.Dataset``), or the value
            (``layouts.RetrievalDataset``) for the database/queries protocol.
        runs, database, unknown_share: the protocol's options, as ``pipeline.run_protocol`` takes them.
    """
    if protocol == "database-queries":
        return dataset.n_queries * dataset.n_database
    n = int((places.image_place >= 0).sum())
    if protocol == "traversal":
        n_db = max(1, dataset.n_traversals - 1) if database is None else len(database)
        return dataset.n_frames * n_db * dataset.n_frames
    if protocol == "open-set":  # one query per place against the known places' images less one each
        known = places.n_places - int(round(unknown_share * places.n_places))
        training = round(n * known / max(1, places.n_places)) - known
        return int(runs) * places.n_places * max(0, training)
    return n * n
