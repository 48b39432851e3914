"""Evaluation protocols: descriptors and places in, a frozen ``Evaluation`` out.

* ``evaluation``: the paper's seeded random splits (closed set), the traversal protocol,
  the open set and the database/queries protocol; Recall@K, rejection, precision.
* ``scale``: the paper protocol in one blocked pass over all image pairs (Nordland scale),
  the same numbers without an N×N matrix.
* ``shared_scores``: the image pairs' scores every protocol run on one set of descriptors
  shares, and a split's negative statistics taken from them pairwise.
* ``precision_recall``: precision–recall curves (global θ, θ_p(k)), AUC, R@100P, R@99P, max F1.
* ``sweep``: one protocol over a grid of group × step, in both readings.
* ``compare``: runs side by side: records, metric tables, differences, exports with settings.
"""
