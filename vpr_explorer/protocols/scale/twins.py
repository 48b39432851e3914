"""Places whose training images are byte-identical ("twins"), which get one θ.

The straightforward computation gives such places the very same θ (same inputs, same
operations), so their margins tie exactly and the tie goes to the lower place id; the
float32 rounding in the downdated σ would break that tie. Content classes are found once
per run (``content_classes``), the twins of each split from them (``twins``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vpr_explorer.method.stats import NegativeStats
from vpr_explorer.method.thresholds import ThresholdMethod, place_thresholds
from vpr_explorer.protocols.scale.layout import GATHER_ROWS, Layout


@dataclass(frozen=True, eq=False)
class Content:
    """The slots' content classes, and the places that can have a twin.

    Attributes:
        classes: ``(P, m)`` a class per slot: equal for byte-identical descriptors, ``-1``
            for padding.
        shared: place indices, ascending, with a slot whose class another place has too.
    """

    classes: np.ndarray
    shared: np.ndarray


def shared_places(classes: np.ndarray) -> np.ndarray:
    """Place indices with a slot whose content class appears in another place as well.

    Only they can have a twin: any other place trains, in every split, on an image that no
    other place holds.
    """
    n_p = classes.shape[0]
    place, _ = np.nonzero(classes >= 0)
    pairs = np.unique(classes[classes >= 0] * n_p + place)  # distinct (class, place), class-major
    cls = pairs // n_p
    in_many = np.bincount(cls)[cls] > 1
    return np.unique(pairs[in_many] % n_p)


def content_classes(d: np.ndarray, lay: Layout) -> Content:
    """A class per slot (``(P, m)``: equal for byte-identical descriptors, ``-1`` for padding),
    and the places that share a class with another place (``shared_places``)."""
    real = np.flatnonzero(lay.image_of_row >= 0)
    img = lay.image_of_row[real]
    w = np.random.default_rng(0).standard_normal(d.shape[1])
    key = np.empty(len(real))
    for lo in range(0, len(real), GATHER_ROWS):
        x = np.asarray(d[img[lo : lo + GATHER_ROWS]], dtype=np.float64)
        key[lo : lo + GATHER_ROWS] = np.einsum("ij,j->i", x, w)
    order = np.argsort(key, kind="stable")
    new = np.r_[True, key[order][1:] != key[order][:-1]]
    run = np.cumsum(new) - 1
    # equal keys: confirm byte equality with the run's first row
    first = order[np.flatnonzero(new)][run]
    clash = np.zeros(len(order), dtype=bool)
    shared = np.flatnonzero(np.bincount(run)[run] > 1)  # a key of one image needs no check
    for lo in range(0, len(shared), GATHER_ROWS):
        at = shared[lo : lo + GATHER_ROWS]
        a = np.ascontiguousarray(d[img[order[at]]])
        b = np.ascontiguousarray(d[img[first[at]]])
        clash[at] = np.any(a.view(np.uint8) != b.view(np.uint8), axis=1)
    sorted_cls = run.copy()
    fresh = int(run.max()) + 1
    for k in np.unique(run[clash]):  # a key shared by different descriptors (vanishingly rare)
        members = np.flatnonzero(run == k)
        rows = np.ascontiguousarray(d[img[order[members]]])
        _, sub = np.unique(rows.view(np.uint8).reshape(len(rows), -1), axis=0, return_inverse=True)
        sorted_cls[members] = fresh + sub.ravel()
        fresh += int(sub.max()) + 1
    cls = np.empty(len(real), dtype=np.int64)
    cls[order] = sorted_cls
    content = np.full((len(lay.places), lay.slots), -1, dtype=np.int64)
    content[lay.place_of_row[real], lay.slot_of_row[real]] = cls
    return Content(content, shared_places(content))


def twins(content: Content, held: np.ndarray) -> np.ndarray:
    """``(P,)`` for each place, the first place whose training images are the same, in order.

    Only the places that share a content class with another place are compared (the others
    are their own first); none at all on routes without repeated frames.

    Args:
        content: the slots' content classes (``content_classes``).
        held: ``(P,)`` held-out slot of each place in this split.
    """
    first_twin = np.arange(len(held))
    shared = content.shared
    if len(shared) > 1:
        classes = content.classes[shared]
        k = np.arange(classes.shape[1] - 1)[None, :]
        seq = np.where(k < held[shared, None], classes[:, :-1], classes[:, 1:])  # the training slots, in order
        _, first, inverse = np.unique(seq, axis=0, return_index=True, return_inverse=True)
        first_twin[shared] = shared[first[inverse.ravel()]]
    return first_twin


def thresholds_with_twins(stats: NegativeStats, method: ThresholdMethod, lay: Layout,
                          first_twin: np.ndarray) -> np.ndarray:
    """``place_thresholds``, with places whose training images are identical given one θ.

    Args:
        stats: one split's negative statistics.
        method: the per-place threshold.
        lay: the layout.
        first_twin: ``(P,)`` each place's first twin (``twins``).

    Returns:
        ``(n_places,)`` θ per place id, a twin's that of its first twin.
    """
    theta = place_thresholds(stats, method)
    theta[lay.places] = theta[lay.places[first_twin]]
    return theta
