"""The graph-based sequence matcher of Vysotska et al.: the cheapest path through the cost matrix, query by query.

Source: Vysotska, Naseer, Spinello, Burgard & Stachniss, "Efficient and effective matching of
image sequences under substantial appearance change" (ICRA 2015), as the authors' public code
computes it (ovysotska/image_sequence_matcher: ``src/graph.py``, ``src/topological_sorting.py``,
``src/path_tools.py``) and as the reimplementation NickTrinh/VPR_Tutorial runs it
(``experiments/vysotska_sequence_matcher.py``, called by ``run_vysotska`` in
``experiments/final_all_datasets.py`` with fanout 5). Every matrix is ``(n_queries, n_database)``,
both axes in route order:

1. **Cost.** C = 1 − S, the similarity turned into a cost (lower is better), in float64
   (NickTrinh's reimplementation subtracts and sums in the matrix's own dtype, float32 for
   float32 similarities; the authors' code reads its cost matrix as float64).
2. **Nodes.** A source, one node (q, j) per query q and database image j, and a target.
3. **Edges**, each carrying the cost of the node it enters:

   * source → (0, j) for every j, weight C[0, j]: the path may start anywhere;
   * (q, j) → (q + 1, k) for k = max(0, j − F) … min(n_database, j + F) − 1, weight
     C[q + 1, k]: the fan-out, the reference's ``range(j - fanout, j + fanout)``. From one
     query to the next the path stays, moves back up to F database images, or forward up to
     F − 1 (the reference's docstring speaks of 2F + 1 children; its code, and NickTrinh's
     copy of it, build the 2F above, and so does this module). With F = 1 the path can only
     stay or step back; a fanout of at least n_database reaches every image;
   * (n_queries − 1, j) → target, weight 0: the path may end anywhere.

4. **Hidden (non-matching) nodes.** The paper adds hidden nodes of constant cost, the
   non-matching cost C_nm, that a path may take instead of a poor match; the public code, which
   "only partially implements the paper" (its README), builds none: the path is the cheapest
   through the raw costs whatever C_nm is, and a node on it is *hidden* when C[q, j] ≥ C_nm
   (``path_tools.filterPath``: matched when C < C_nm, an exact comparison, so a cost exactly at
   C_nm is hidden). A hidden node continues like any other, through the same fan-out, its own
   cost counted in full. C_nm therefore decides which queries are reported (``matched`` −1 for
   a hidden node), never the path or its cost.
5. **Shortest path.** The rows are a topological order of the graph (every edge goes one query
   down), so the shortest path is a dynamic programme over queries: D[0, k] = C[0, k];
   D[q, k] = C[q, k] + D[q − 1, j*], j* the best parent among columns k − F + 1 … k + F
   inside the matrix; the path ends at the best node of the last query and is traced back.
   **Ties**: the reference relaxes edges in node order with a strict ``>``, so an exactly
   equal parent (or end node) of a lower column wins. Here the best parent (end node) is the
   lowest column whose D lies within ``TIE_TOLERANCE`` (1e-5) of the minimum (the package's rule
   for every answer, ``method.retrieval``), and D[q, k] adds C[q, k] to that parent's D, so
   ``path_cost`` is the sum of ``node_cost`` along the path (to rounding). A near tie that
   picks the lower column costs less than 1e-5, so ``path_cost`` lies at most
   n_queries × 1e-5 above the exact minimum (equal to it where no near tie arises).

**The full pipeline** (``full_pipeline``, NickTrinh's ``run_vysotska``): each query's smoothed
adaptive threshold θ_q (``query_threshold.query_thresholds``), C_nm = 1 − median over queries of
θ_q, then the path with fanout 5. A node is then matched when 1 − S < 1 − median θ, i.e. its
similarity lies above the median threshold (to rounding).

**Order matters**: the path follows both sequences, so the queries and the database must each
be one traversal in route order (``sequences.check_sequence`` checks a dataset value; these
functions take matrices and cannot).

**Cost.** One pass over the queries, each vectorised over the database: the previous row of D
padded with ∞ and read through 2F shifted views, one ``np.minimum`` and one comparison per view;
O(n_queries · n_database · F) time, memory one row of D and the chosen parent of every node as a
``(n_queries, n_database)`` offset in [0, 2F) (one byte for F ≤ 128). Nordland winter against
summer, pixels (3,576 × 3,576, F = 5): 0.27 s on one core, 1.3× the similarity matrix (0.21 s,
float32 GEMM on two cores).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vpr_explorer.errors import VPRInputError, finite_number
from vpr_explorer.method.query_threshold import QueryThresholdSpec, query_thresholds
from vpr_explorer.method.retrieval import TIE_TOLERANCE

#: Fan-out F (``run_vysotska``'s, the reference README's typical value; its command line's default is 3).
FANOUT = 5


@dataclass(frozen=True, eq=False)
class GraphMatch:
    """The cheapest path and what it decides, each array ``(n_queries,)``.

    Attributes:
        matched: the database image of each query, ``-1`` where the path goes through a hidden
            node (cost ≥ the non-matching cost).
        path: the database image the path takes at each query, hidden or not.
        node_cost: the cost 1 − S[q, path[q]] of that node.
        path_cost: the path's cost, the sum of ``node_cost`` (module doc, step 5).
        non_matching_cost: C_nm, the cost from which a node on the path is hidden.
    """

    matched: np.ndarray
    path: np.ndarray
    node_cost: np.ndarray
    path_cost: float
    non_matching_cost: float

    def __post_init__(self) -> None:
        for a in (self.matched, self.path, self.node_cost):
            a.setflags(write=False)

    @property
    def hidden(self) -> np.ndarray:
        """``(n_queries,)`` bool: the path goes through a hidden node at this query."""
        return self.matched < 0


def sequence_match(similarity: np.ndarray, *, non_matching_cost: float, fanout: int = FANOUT) -> GraphMatch:
    """The cheapest path from the first query to the last through C = 1 − S (module doc).

    Args:
        similarity: ``(n_queries, n_database)`` similarities, both axes in route order.
        non_matching_cost: C_nm: a node on the path whose cost 1 − S is at least this is hidden.
        fanout: F: from one query to the next the path moves at most F images back, F − 1 forward.
    Returns:
        The path, its costs and the matched database image of each query.
    Raises:
        VPRInputError: a matrix that is not 2-D and non-empty or holds NaN or infinite values, a
            fanout below 1 or not a whole number, a non-matching cost that is not a finite number.
    """
    s = _matrix(similarity)
    nmc = finite_number(non_matching_cost, "non_matching_cost")
    f = _fanout(fanout)
    nq, nd = s.shape
    reach = min(f, nd)  # a fanout of n_database already reaches every image
    width = 2 * reach
    # pad[reach − 1 + j] holds D[q − 1, j]: pad[o + k] is parent k − reach + 1 + o of node k, o = 0 … 2F − 1
    pad = np.full(nd + width - 1, np.inf)
    shifted = [pad[o:o + nd] for o in range(width)]
    columns = np.arange(nd)
    choice = np.zeros((nq, nd), dtype=np.min_scalar_type(width - 1))
    floor = np.empty(nd)
    near = np.empty(nd, dtype=bool)
    dist = 1.0 - s[0].astype(np.float64)
    for q in range(1, nq):
        pad[reach - 1:reach - 1 + nd] = dist
        np.copyto(floor, shifted[0])
        for parents in shifted[1:]:
            np.minimum(floor, parents, out=floor)
        floor += TIE_TOLERANCE
        pick = choice[q]
        for o in range(width - 1, -1, -1):  # downwards, so the lowest column within the tolerance is written last
            np.less_equal(shifted[o], floor, out=near)
            np.copyto(pick, o, where=near)
        dist = pad[columns + pick]
        dist += 1.0 - s[q].astype(np.float64)
    end = int(np.argmax(dist <= dist.min() + TIE_TOLERANCE))
    path = np.empty(nq, dtype=np.int64)
    path[-1] = end
    for q in range(nq - 1, 0, -1):
        path[q - 1] = path[q] - reach + 1 + int(choice[q, path[q]])
    node_cost = 1.0 - s[np.arange(nq), path].astype(np.float64)
    matched = np.where(node_cost < nmc, path, -1)
    return GraphMatch(matched=matched, path=path, node_cost=node_cost, path_cost=float(dist[end]),
                      non_matching_cost=nmc)


def full_pipeline(similarity: np.ndarray, *, fanout: int = FANOUT,
                  spec: QueryThresholdSpec | None = None) -> tuple[GraphMatch, float]:
    """Per-query thresholds, C_nm = 1 − their median, then the cheapest path (module doc, the full pipeline).

    Args:
        similarity: ``(n_queries, n_database)`` similarities, both axes in route order.
        fanout: F of ``sequence_match``.
        spec: the settings of ``query_threshold.query_thresholds`` (default ``QueryThresholdSpec()``).
    Returns:
        The match, and the non-matching cost C_nm it used.
    Raises:
        VPRInputError: as ``sequence_match`` and ``query_thresholds``.
    """
    f = _fanout(fanout)
    s = _matrix(similarity)
    thresholds = query_thresholds(s, spec).threshold
    nmc = 1.0 - float(np.median(thresholds))
    return sequence_match(s, non_matching_cost=nmc, fanout=f), nmc


# --------------------------------------------------------------------------- checks


def _matrix(matrix: object) -> np.ndarray:
    """The similarity matrix as a real array (float32 stays float32: rows are widened one at a time)."""
    try:
        m = np.asarray(matrix)
    except (TypeError, ValueError):
        raise VPRInputError("similarity must be a numeric (n_queries, n_database) matrix") from None
    if m.dtype.kind not in "fiu":
        raise VPRInputError(f"similarity must be a real (n_queries, n_database) matrix, got dtype {m.dtype}")
    if m.ndim != 2 or 0 in m.shape:
        raise VPRInputError(f"similarity must be a non-empty 2-D (n_queries, n_database) matrix, got shape {m.shape}")
    if m.dtype.kind != "f":
        m = m.astype(np.float64)
    if not np.isfinite(m).all():
        raise VPRInputError("similarity holds NaN or infinite values: the path needs every pair's cost; "
                            "recompute it from finite descriptors")
    return m


def _fanout(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise VPRInputError(f"fanout must be a whole number ≥ 1 (database images per query; the reference uses "
                            f"{FANOUT}), got {value!r}")
    return int(value)
