"""Datasets in: every layout read into a value, with its ground truth.

* ``traversals``: route traversals (folders of frames where the same index is the same spot)
  and prepared ``Place####_Cond##_G##`` folders -> ``Dataset``.
* ``layouts``: the field's benchmark layouts (database-queries, VPR-Bench,
  traversal-positions, manifest) -> ``RetrievalDataset``, with its ``GroundTruth``.
* ``groundtruth``: which database images are right for which query (``GroundTruth``), from
  frames ± a tolerance, positions within a radius, or given lists.
* ``safe_npy``: reading ``.npy`` files without running anything stored in them.
* ``catalogue``: the public datasets the explorer knows (home, licence, size, layout, URLs, sha256).
* ``fetch``: downloading one of them (resumable, checked, unpacked safely) into the data folder.
* ``demo``: the built-in demo route, a small drawn street, so the app and CLI run with no download.
* ``example_layouts``: GardensPoint Walking written in each layout, for worked examples and tests.
* ``example_million``: a synthetic position-tagged database of any size (the million-image benchmark).
"""
