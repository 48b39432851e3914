"""Evaluation protocols: descriptors and places in, a frozen ``Evaluation`` out.

* ``options``: ``ProtocolOptions``, the one settings value every protocol run takes, and
  its defaults (the paper's 50 runs, …).
* ``evaluation``: the paper's seeded random splits (closed set), the open set and the
  database/queries protocol (the traversal protocol is it on aligned traversals); Recall@K,
  rejection, precision.
* ``scale``: the paper protocol in one blocked pass over all image pairs (Nordland scale),
  the same numbers without an N×N matrix.
* ``shared_scores``: the image pairs' scores every protocol run on one set of descriptors
  shares, and a split's negative statistics taken from them pairwise.
* ``precision_recall``: precision–recall curves (global θ, θ_p(k)), AUC, R@100P, R@99P, max F1.
* ``tutorial_pr``: VPR_Tutorial's precision–recall: single- and multi-match, soft ground
  truth as "ignore".
* ``acceptance``: the acceptance bench: every acceptance rule (the paper's, the authors'
  follow-up's, the per-query threshold and graph matcher, SeqSLAM, the training-free match
  scores) on the same queries, closed set and natural open set, the authors' counts.
* ``acceptance_sweep``: the acceptance bench over the values of one of its parameters
  (sequence length, patch, fan-out, SUE's K, the reference share, group/step).
* ``sweep``: one protocol over a grid of group × step, in both readings.
* ``cost``: the image pairs a protocol run scores, said before it runs.
* ``compare``: runs side by side: records, metric tables, differences, exports with settings.
* ``paired``: a rate over splits (mean ± std and its 95% interval), and two on the same
  splits compared split by split (paired t-test), or marked where the splits differ.
* ``many``: every dataset × descriptor × protocol in one run (``vpr-explorer bench``).
"""
