"""The paper's method and the field's other acceptance rules: places, statistics, thresholds, decisions.

* ``places``: group/step (stride and skip readings) make places of frames, of database
  images, or of metres along a route or on a lattice (``Places``, ``retrieval_places``).
* ``stats``: each training image's negative similarity statistics in closed form, and the
  place's negative Gaussian mixture M(p).
* ``thresholds``: per-place θ_p (simple, weighted), the family θ_p(k), adaptive k, the
  automatic global θ and its training-pair sample.
* ``auto_theta``: why the automatic global θ is what it is (its median and MAD), and when
  it rejects every query.
* ``retrieval``: every method (image- and place-level baselines, filter-then-rank), place
  scores (the best or the mean similarity of a place's images), pessimistic ranks, ``QueryDecision`` records that explain themselves.
* ``database``: a database with its per-place thresholds, and what one method's answer to
  one query was (``Verdict``).
* ``place_discovery``: places discovered online from the reference stream (the authors'
  follow-up), beside group/step.
* ``match_scores``: training-free match scores: the top-1 distance, the PA-ratio, SUE.
* ``query_threshold``: the per-query adaptive threshold of Vysotska et al. (a patch's
  two-component mixture, smoothed along the sequence).
* ``sequences``: SeqSLAM as OpenSeqSLAM defines it, and sequence-aggregated place scores.
* ``graph_matcher``: the graph-based sequence matcher of Vysotska et al. (the cheapest path
  through the cost matrix with a bounded fan-out; nodes above the non-matching cost hidden).
"""
