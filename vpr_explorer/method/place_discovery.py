"""Places discovered online from the database stream (Trinh & Lyons' follow-up, ``OnlinePlaceDiscovery``).

Instead of group/step, the database images, taken in route order, are cut into places as
they arrive: a frame joins the current place while its similarity to the place stays above
a threshold drawn from the place's running negative statistics, and a new place starts when
``hysteresis`` frames in a row fall to or below it. The authors' public description: a
bootstrap with factor α = 1.5, then online with minimum place size m = 2 and hysteresis
h = 2, statistics updated incrementally (Welford). Their code
(NickTrinh/VPR_Tutorial, ``experiments/online_place_discovery.py``) fixes what the
description leaves open; this module follows it, and says so item by item.

**Bootstrap (place 0, then place 1).** Frame 0 opens place 0. For each later frame T the
consecutive similarity c_T = s(T−1, T) is kept. From T = m + 1 on, frame T is a *dip* when
``c_T < mean(c_1..c_{T−1}) − α·std(c_1..c_{T−1})`` (strict; population std, ddof 0; a
fixed std of 0.1 while fewer than 3 earlier values exist). Until the first dip every frame
joins place 0 (so place 0 holds at least m + 1 frames); the dip frame opens place 1, which
takes the next frames unconditionally until it holds m frames — at least 2, as their code
checks the size only from the frame after the dip on; then the online phase starts.
Consecutive similarities play no further part. A stream with no dip is one place. ``m``
is used here only: the online phase has no minimum place size and never merges places (a
place born online holds at least h frames; a run of fewer than h frames below θ returns to
the current place, see hysteresis).

**Online (every later frame T).**

* Score: the mean cosine similarity of frame T to the current place's frames, i.e. the dot
  product with the place's mean descriptor (frames still pending, below, are not in it).
* Statistics of the current place, computed when it is opened and updated only when a frame
  stays (never while frames are pending):
  - negative value of a frame: its mean similarity to every frame of every earlier place
    (every frame before the place's first one); μ⁻, σ⁻ = running mean and population std of
    those values over the place's frames (σ⁻ = 0.1 while fewer than 2 values);
  - positive value: for the frames that open the place, the mean similarity to the place's
    other opening frames (none with a single opening frame: μ⁺ = 0 then); for a frame that
    stays, its mean similarity to the place *including itself* (similarity 1) and the
    pending frames merged back just before it — the authors' code does exactly this; μ⁺ =
    running mean.
  - Frames merged back from a false alarm add to the place but not to μ⁻, σ⁻ or μ⁺ (only
    the frame that ends the false alarm is counted).
* Threshold: ``θ = μ⁻ + n·σ⁻`` with ``n = clip(floor((μ⁺ − μ⁻)/σ⁻), 0, cap)``, cap = 10
  (their ``filter_n_cap``); n = 1 when σ⁻ < 1e-8. (Not the recognition threshold's
  ``k = clip(sep/2, 1, 2)``: discovery uses this floor rule.)
* Hysteresis: a frame with ``score <= θ`` (at the threshold counts as below) is pending; h
  pending frames in a row open a new place made of exactly those h frames, whose
  statistics are computed as above; a frame above θ returns every pending frame to the
  current place, then joins it.
* End of stream: frames still pending (fewer than h) belong to no place (label −1); at most
  h − 1 trailing frames, and only if the route ends in a drop.

Defaults: α = 1.5, m = 2, h = 2 (the authors' published runs, ``final_all_datasets.py``;
their class's own default is m = 3), cap = 10. Rows are L2-normalised here as their code
does (descriptors from this package already are). Places come out as contiguous runs in
route order, ids 0..P−1 in order of discovery.

Cost: consecutive similarities are one vectorised pass; each frame then costs O(D) (dot
products with running sums of descriptors: the mean similarity to a set of unit rows is the
dot product with their sum over their count), plus O(h²·D) when a place opens. A Python
loop runs over the stream, as the algorithm is sequential.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.stats import validate_descriptors

ALPHA = 1.5
"""Bootstrap factor α: a dip is a consecutive similarity below mean − α·std of the earlier ones."""
MIN_SIZE = 2
"""m: the bootstrap checks for a dip from frame m + 1 on, and place 1 takes max(m, 2) frames before going online."""
HYSTERESIS = 2
"""h: frames in a row at or below θ that open a new place."""
CAP = 10.0
"""Largest n in θ = μ⁻ + n·σ⁻ (the authors' ``filter_n_cap``)."""
STD_FALLBACK = 0.1
"""The std the authors' code uses when too few values exist (bootstrap: < 3; a place's σ⁻: < 2)."""
MIN_STD = 1e-8
"""Below this σ⁻ the authors' code takes n = 1."""


@dataclass(frozen=True, eq=False)
class Discovery:
    """Places discovered from a database stream, and what decided them.

    Attributes:
        place: ``(n_database,)`` int64 place of each image, ids ``0..n_places-1`` in route
            order; ``-1`` for trailing frames still pending when the stream ended.
        n_places: number of places.
        consecutive: ``(n_database,)`` similarity of each frame to the one before (NaN at 0).
        score: ``(n_database,)`` online score of each frame (mean similarity to the current
            place); NaN for bootstrap frames.
        theta: ``(n_database,)`` the threshold that score was compared with; NaN for
            bootstrap frames.
        online_from: first frame of the online phase (``n_database`` if it never starts).
    """

    place: np.ndarray
    n_places: int
    consecutive: np.ndarray
    score: np.ndarray
    theta: np.ndarray
    online_from: int

    def __post_init__(self) -> None:
        for a in (self.place, self.consecutive, self.score, self.theta):
            a.setflags(write=False)

    @property
    def sizes(self) -> np.ndarray:
        """``(n_places,)`` images in each place."""
        return np.bincount(self.place[self.place >= 0], minlength=self.n_places)


class _Running:
    """Welford's running mean and population std (the authors' ``RunningStats``)."""

    __slots__ = ("n", "mean", "m2")

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0

    def add(self, x: float) -> None:
        self.n += 1
        delta = x - self.mean
        self.mean += delta / self.n
        self.m2 += delta * (x - self.mean)

    def std(self, fallback: float) -> float:
        return math.sqrt(self.m2 / self.n) if self.n >= 2 else fallback


def _check(alpha, min_size, hysteresis, cap) -> None:
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.integer, np.floating)) \
            or not math.isfinite(alpha) or alpha < 0:
        raise VPRInputError(f"alpha={alpha!r}: the bootstrap factor must be a finite number >= 0 (default {ALPHA})")
    for name, value in (("min_size", min_size), ("hysteresis", hysteresis)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise VPRInputError(f"{name}={value!r}: must be a whole number of frames, 1 or more")
    if isinstance(cap, bool) or not isinstance(cap, (int, float, np.integer, np.floating)) \
            or not math.isfinite(cap) or cap < 0:
        raise VPRInputError(f"cap={cap!r}: the largest multiple of σ⁻ must be a finite number >= 0 "
                            f"(default {CAP:g})")


def discover(descriptors: np.ndarray, alpha: float = ALPHA, min_size: int = MIN_SIZE,
             hysteresis: int = HYSTERESIS, cap: float = CAP) -> Discovery:
    """Cut a database stream into places online (the module docstring gives the rule).

    Args:
        descriptors: ``(n_database, D)`` descriptors of the database images in route order
            (rows are L2-normalised here). Consecutive similarities alone would not do: the
            score and the negative values need similarities to whole places.
        alpha: bootstrap factor α (>= 0).
        min_size: m, frames before the bootstrap looks for a dip, and place 1's size, at least 2 (>= 1).
        hysteresis: h, frames in a row at or below θ that open a new place (>= 1).
        cap: the largest n in θ = μ⁻ + n·σ⁻ (>= 0).

    Returns:
        The ``Discovery``: each image's place and the scores and thresholds behind it.

    Raises:
        VPRInputError: descriptors not a non-empty 2-D array, with NaN/inf or all-zero rows;
            a parameter out of range.
    """
    _check(alpha, min_size, hysteresis, cap)
    x = np.asarray(validate_descriptors(descriptors, "descriptors"), dtype=np.float64)
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    n = len(x)
    h, m, alpha, cap = int(hysteresis), int(min_size), float(alpha), float(cap)
    place = np.full(n, -1, dtype=np.int64)
    consecutive = np.full(n, np.nan)
    consecutive[1:] = np.einsum("ij,ij->i", x[:-1], x[1:])
    score = np.full(n, np.nan)
    theta = np.full(n, np.nan)

    # bootstrap: place 0 until the first dip
    place[0] = 0
    base = _Running()
    dip = n
    for t in range(1, n):
        c = consecutive[t]
        if t >= m + 1:
            spread = base.std(0.0) if base.n > 2 else STD_FALLBACK
            if c < base.mean - alpha * spread:
                dip = t
                break
        base.add(c)
        place[t] = 0
    if dip == n:
        return Discovery(place, 1, consecutive, score, theta, n)
    # the dip frame opens place 1; the authors' code checks its size from the next frame on,
    # so it takes max(m, 2) frames
    first = min(dip + max(m, 2), n)
    place[dip:first] = 1
    if first == n:
        return Discovery(place, 2, consecutive, score, theta, n)

    def open_place(a: int, b: int, before: np.ndarray) -> tuple[np.ndarray, int, _Running, _Running]:
        """Sum and count of frames a..b-1, and their statistics (``before``: the sum of frames 0..a-1)."""
        block = x[a:b]
        neg, pos = _Running(), _Running()
        for v in block @ before / a:
            neg.add(float(v))
        if b - a >= 2:
            gram = block @ block.T
            others = (gram.sum(axis=1) - np.diag(gram)) / (b - a - 1)
            for v in others:
                pos.add(float(v))
        return block.sum(axis=0), b - a, neg, pos

    def threshold(neg: _Running, pos: _Running) -> float:
        mu, sd = neg.mean, neg.std(STD_FALLBACK)
        k = 1.0 if sd < MIN_STD else float(math.floor((pos.mean - mu) / sd))
        return mu + max(min(k, cap), 0.0) * sd

    starts = [0, dip]
    before_sum, before_n = x[:dip].sum(axis=0), dip
    place_sum, place_n, neg, pos = open_place(dip, first, before_sum)
    th = threshold(neg, pos)
    pending = 0
    for t in range(first, n):
        xt = x[t]
        s = float(xt @ place_sum) / place_n
        score[t], theta[t] = s, th
        if s <= th:
            pending += 1
            if pending >= h:
                a = t - h + 1
                before_sum, before_n = before_sum + place_sum, a
                starts.append(a)
                place_sum, place_n, neg, pos = open_place(a, t + 1, before_sum)
                th = threshold(neg, pos)
                pending = 0
            continue
        if pending:
            place_sum = place_sum + x[t - pending : t].sum(axis=0)
            place_n += pending
            pending = 0
        place_sum = place_sum + xt
        place_n += 1
        pos.add(float(xt @ place_sum) / place_n)
        neg.add(float(xt @ before_sum) / before_n)
        th = threshold(neg, pos)
    assigned = n - pending
    place[:assigned] = np.searchsorted(np.asarray(starts), np.arange(assigned), side="right") - 1
    place[assigned:] = -1
    return Discovery(place, len(starts), consecutive, score, theta, first)


def discovered_places(descriptors: np.ndarray, alpha: float = ALPHA, min_size: int = MIN_SIZE,
                      hysteresis: int = HYSTERESIS, cap: float = CAP) -> tuple[np.ndarray, int]:
    """``(n_database,)`` place of each database image, discovered online, and the number of places.

    The same form as ``places.retrieval_places``: contiguous runs along the route, ids
    ``0..n_places-1``; ``-1`` only for trailing frames still pending when the stream ends
    (fewer than ``hysteresis``).

    Args:
        descriptors: ``(n_database, D)`` database descriptors in route order.
        alpha, min_size, hysteresis, cap: as in ``discover``.

    Returns:
        ``(place, n_places)``.

    Raises:
        VPRInputError: bad descriptors or parameters (``discover``), or fewer than 2 places
            discovered (negative statistics need at least 2).
    """
    found = discover(descriptors, alpha=alpha, min_size=min_size, hysteresis=hysteresis, cap=cap)
    if found.n_places < 2:
        raise VPRInputError(
            f"place discovery (alpha={alpha:g}, min_size={min_size}, hysteresis={hysteresis}) found "
            f"{found.n_places} place in {len(found.place)} database images: negative statistics need at least 2; "
            "lower alpha, or use group/step places"
        )
    return np.array(found.place), found.n_places
