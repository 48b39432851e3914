"""The paper protocol at Nordland scale: one blocked pass over all image pairs.

``fast_paper_protocol`` returns the numbers of ``evaluation.paper_protocol`` — same seeded
splits, the same float32 similarities, the same thresholds (to float rounding), ranks, tie
rules and answers — without an N×N matrix and without a pass per split. At Nordland g3s3's
110,000 images the straightforward protocol does, per split, an N×D² gram and a 9,197 × N
similarity; this package does one pass over the image pairs for all splits.

Files, in the order data moves
------------------------------
How the pass runs (rows per block, table memory, threads, device) is part of the run's one
``protocols.options.ProtocolOptions``, checked when it is made.

``layout``        ``Layout``: the labelled images place by place, slot-padded, in blocks of
                  whole places; ``as_layout32``, its float32 copy, which the pass reads.
``full_sums``     ``full_set_sums``: the float64 sums over all images, once (step 1); with
                  ``ProtocolOptions.device``, in torch float64 there (``device_set_sums``).
``table``         the top-2 table the pass files and the scoring reads: ``Entries`` (in RAM,
                  then a temporary file), ``NearSlots``, ``Records``; ``TIE``, ``round_down32``.
``panel``         ``panel_task``: one panel of the pass, a GEMM and its squares, downdate
                  products and maxima, slab by slab (step 2).
``device_panel``  ``DevicePanels``: the same panel on a torch device, in whole-panel tensor
                  operations (step 2, with ``ProtocolOptions.device``).
``blocked_pass``  ``blocked_pass``: every panel of every block pair, in threads, merged in
                  task order into V, b and the table (step 2).
``twins``         places whose training images are byte-identical, which get one θ.
``downdate``      per split: μ, σ and the thresholds from the downdated moments (steps 1, 3).
``near_ties``     each weighted θ's error bound, and its float64 recomputation (step 6).
``scoring``       per split and row block: the candidates, every method's ranks and answers,
                  the near ties made exact, the ``SplitScores`` (steps 5, 6).
``protocol``      the entry points ``scale_splits`` and ``fast_paper_protocol``: the steps in
                  order.

Algorithm
---------
A split holds exactly one image of every place out (the query) and trains on the rest.
``protocol`` runs the steps below as 1 (full-set sums; 4, the automatic θ, beside them in a
second thread), 2, 1 and 3 (per split), 6 (error bounds), then 5 and 6 together; the
functions doing each step are named at its end.

1. **Negative statistics by downdating** (the closed form of ``method.stats``). From the
   full-set sums T = Σⱼ dⱼ, T_p, C = Σⱼ dⱼdⱼᵀ and aᵢ = Σ_{j∉p(i)} (dᵢ·dⱼ − c)² (from dᵢᵀCdᵢ,
   float64, once; c is the mean score, a float32 value), a training image i of place p in
   split r (queries Q_r, p's held-out image h) has

       n⁻ᵢ μᵢ             = dᵢ·(T − T_p) − dᵢ·Σ_{q∈Q_r} d_q + dᵢ·d_h
       n⁻ᵢ E[(s − c)²]ᵢ   = aᵢ − V_{i,r},    V_{i,r} = Σ_{q∈Q_r, p(q)≠p} (dᵢ·d_q − c)²
       σᵢ²                = E[(s − c)²]ᵢ − (μᵢ − c)²

   so no split forms a D×D gram: dᵢ·Σ_q d_q for all splits is one (N×D)·(D×R) product,
   dᵢᵀCdᵢ is dᵢᵀWdᵢ with W block upper triangular (``stats.triangular_blocks``: float64
   GEMMs, (1 + 1/8)·N·D² flops instead of 2·N·D²), and V comes out of the pass (2). With
   ``ProtocolOptions.device`` these sums are torch float64 products on that device (dᵢᵀCdᵢ
   through the full C there), which differ from numpy's by float64 rounding only (under
   1e-14 of their terms' magnitudes). μ, hence the simple θ, is exact to float64 rounding;
   σ carries the float32 rounding of the scores in V (taken about c, so descriptors whose
   scores all sit near 0.8 lose no more than centred ones), which moves a weighted θ_p by
   ~1e-11 (synthetic) to ~2e-9 (Nordland pixels). Step 6 keeps that from changing any
   outcome. Places whose training images are byte-identical get one θ, as in the reference
   (same inputs, same operations: their margins tie exactly). ``full_set_sums`` (on a
   device ``device_set_sums``), ``split_mu``, ``downdated_sigma``; twins:
   ``content_classes``, ``twins``.
2. **One blocked pass** over the block pairs I ≤ J of the place-major layout (``Layout``).
   S = X_I X_Jᵀ in float32. Its scores may differ from the reference's in the last bits
   (the BLAS kernel, block shape and threads change the summation order): every tie and
   answer is therefore decided with ``retrieval.TIE_TOLERANCE``, which such differences
   never cross, so the outcomes are the reference's. Each block pair is cut into panels of
   whole places of block I (``PANEL_ROWS`` rows, every slot of each place; on a diagonal
   block, panels ``DIAGONAL_SPLIT`` times shorter, each against the block's places from its
   own on, so that the block's GEMMs cover little more than its triangle): a panel is one
   GEMM in one thread, read after it slab by slab (``SLAB_ROWS`` rows of one slot, which
   stay in cache) for everything below; panels run side by side in ``threads`` threads
   (BLAS in one thread each) and are merged in task order, so the sums and the table are
   the same for any number of threads. With ``ProtocolOptions.device`` each panel runs on
   that torch device instead (``DevicePanels``): the GEMM, the squares, both downdate products
   (dense there, float32 over ``W_CHUNK`` rows or columns, summed in float64), the masks, b,
   both maxima and the selection of the table's entries with their top 2, in whole-panel
   operations on panels of ``DEVICE_PANEL_ROWS`` rows; only the floors and the merge stay on
   the CPU, and the panels' results are the numpy panels' (V to the rounding of its float32
   sums, whose order differs). Each panel gives, for its rows and, by symmetry, block J's
   rows:

   * V (above): ((S − c)∘(S − c)) @ M, same-place pairs zeroed, with M the (N × R) query
     indicator: for the panel's rows, float32 products over chunks of ``W_CHUNK`` columns
     (one nonzero term per place in the chunk); for block J's, each slab row that is a
     query of split r added to split r's float32 sum (a sparse (R × rows) indicator, about
     R/m rows per split: 1/m of the dense product's flops, ``PassState.slab_queries``),
     one term per place of the panel; both summed in float64 across panels;
   * the **top-2 table**: per (image, place) the best and second-best score and the slots
     reaching them. In split r, raw_p of a query is p's best score unless p's held-out
     image is that best, then the second (on a tie the second equals the best). A query is
     held out of its own place, so its best correct score b_q is split-independent. Where
     two of a place's images score within the tie tolerance (t2 ≥ t1 − tol or
     t3 ≥ t2 − tol: near-duplicate images, rare), the entry keeps all its slot scores
     (``NearSlots``), from which raw_p and its image (the lowest slot within the
     tolerance) follow exactly in every split;
   * for the image-level baseline, the places where two or more images reach b_q, with
     the slots that do (at most max(ks) per image: more, and the rank is beyond every K).

   The table is kept only where it can matter: for images that are a query in some split,
   and above the row's floor. Every exact θ_p is a convex combination of its place's μᵢ,
   so all lie in [min μ, max μ] (known before the pass), and no place below
   b − (max μ − min μ) (or min μ when the own place can be dropped, −∞ when b is) reaches
   any rank or answer. Entries are (row, place, t1, a1, t2, a2, near), 19 bytes each
   (``table.ENTRY``), in RAM up to ``table_memory`` bytes, then in a temporary file.
   ``blocked_pass``, ``panel_task``, ``row_floor``, ``Entries``, ``Records``.
3. **Per split thresholds** from the downdated moments through the library's own
   ``NegativeStats`` and ``place_thresholds``. ``split_thresholds``.
4. **The automatic global θ** is the reference's own: one tile sample for the whole run
   (``thresholds.pooled_pair_sample``: ~2.4·10⁶ scores in dense tiles over every image in a
   place, drawn once), of which each split keeps the pairs of its training images and reads
   median and MAD off the sorted scores; the reference protocol makes the same calls, so the
   θ are equal bit for bit. ``automatic_thetas``.
5. **Per split scoring**, one row block of queries at a time, reads each query's table
   entries at or above its cutoff — the lowest score that can still reach a rank or an
   answer under any method of the split, with every weighted θ anywhere within its error
   bound (6) — and runs every method on those candidates only (the cutoff is a bound, not
   a heuristic). The global θs follow from b, the top raw score and the place baseline.
   ``score_block`` (``candidates``, ``candidate_cutoff``, ``score_place_level``,
   ``score_image_level``), ``assemble``.
6. **Near ties.** Each weighted θ_p gets an error bound: first order in the σ errors,
   scaled by the largest error of V seen when a seeded sample of images is recomputed
   exactly, times ``SAFETY`` (observed errors stay under 3% of the bound), doubled for
   the second-order terms. Where a comparison that a change within those bounds could
   overturn decides a query's outcome (a keep test, a margin against the own place's or
   the top answer's), the places involved get σ, hence θ, recomputed in float64 —
   exactly the closed form — and that row block of that split is scored again, until no
   such comparison is left. ``error_scale``, ``uncertainty``, ``near_tie_places``,
   ``make_exact``, ``score_splits``.

Ranks, ties and answers follow ``retrieval``: scores within ``TIE_TOLERANCE`` tie, ties
count against the query, answers are the lowest index within the tolerance of the best
(place id; image index within a place; image index across places at the image level),
cross-condition queries see other traversals only.
Image-level ranks beyond max(ks) are reported as max(ks) + 1 (Recall@K never needs more).

Tuning constants live in the module that reads them (``blocked_pass.PANEL_ROWS``,
``panel.SLAB_ROWS``, …): set one there to change it for a run.
"""

from vpr_explorer.protocols.scale.layout import Layout, make_layout
from vpr_explorer.protocols.scale.protocol import fast_paper_protocol, scale_splits

__all__ = [
    "Layout",
    "fast_paper_protocol",
    "make_layout",
    "scale_splits",
]
